/*
 * tb_fx_origin_drift.c - effect origin_drift (thermbench.sim.effects.OriginDrift, code 7): the
 * fixed-bearing housing grows and shifts the screw's fixed point, an offset beta (T_h - T_h0).
 * The housing (thermbench.sim.parts.Housing, driven by the fixed bearing, touching the fixed
 * end) is a first-order lag over each macro step of
 *   gain_W qb + gain_v v + coupling theta_fixed_end + (Ta - Ta0)   (step means / start values).
 * Section: beta_um_per_K, housing tau_s (> 0), gain_K_per_W, gain_K_per_mm_min, screw_coupling.
 */
#include "tb_physics.h"

typedef struct {
    tb_real beta, a, gain_w, gain_v, coupling; /* a = exp(-macro / tau) */
    tb_real y;     /* the housing's rise */
    tb_real theta; /* the fixed end's temperature at the step start (the bearing slices' mean) */
} self_t;

static int validate(const tb_model *m, uint32_t at) { return PV(m, at + 1) > 0 ? TB_OK : TB_E_PAYLOAD; }

static void init(void *self, const tb_model *m, uint32_t at, const tbi_phys_par *c)
{
    self_t *s = (self_t *)self;
    s->beta = PV(m, at);
    s->a = tbm_exp(-c->macro / PV(m, at + 1));
    s->gain_w = PV(m, at + 2);
    s->gain_v = PV(m, at + 3);
    s->coupling = PV(m, at + 4);
}

static void step_start(void *self, const tbi_phys_par *c, const tbi_phys *p)
{
    self_t *s = (self_t *)self;
    uint32_t i, nl = c->nb > 0 ? c->nb : 1;
    tb_real s0 = 0;
    for (i = 0; i < nl && i < c->n; i++) s0 += p->theta[i];
    s->theta = s0 / (tb_real)nl;
}

static void step_end(void *self, const tbi_phys_par *c, const tbi_phys *p, tb_real qb_mean, tb_real v_mean)
{
    self_t *s = (self_t *)self;
    tb_real u = s->gain_w * qb_mean + s->gain_v * v_mean + s->coupling * s->theta + p->amb_b_start;
    (void)c;
    s->y = s->a * s->y + (1 - s->a) * u;
}

static tb_real offset(const void *self) { return ((const self_t *)self)->beta * ((const self_t *)self)->y; }

const tbi_effect tbi_effect_origin_drift = {
    .code = 7, .n_params = 5, .self_bytes = sizeof(self_t), .validate = validate, .init = init,
    .step_start = step_start, .step_end = step_end, .offset = offset,
};
