/*
 * tb_fx_free_end_bearing_heat.c - effect free_end_bearing_heat
 * (thermbench.sim.effects.FreeEndBearingHeat, code 5): the support bearing adds friction heat
 * QF = kF v, spread evenly over the last k slices of the screw. Section: kF_W_per_mm_min,
 * k (whole slices, 1..n: ceil(length_m / dx)).
 */
#include "tb_physics.h"

typedef struct {
    tb_real kF, sum;
    uint32_t k;
} self_t;

static int validate(const tb_model *m, uint32_t at)
{
    tb_real k = PV(m, at + 1);
    return k >= 1 && k <= (tb_real)m->dims[1] && k == tbm_floor(k) ? TB_OK : TB_E_PAYLOAD;
}

static void init(void *self, const tb_model *m, uint32_t at, const tbi_phys_par *c)
{
    self_t *s = (self_t *)self;
    (void)c;
    s->kF = PV(m, at);
    s->k = (uint32_t)PV(m, at + 1);
}

static void fine(void *self, const tb_real *v, uint32_t count)
{
    self_t *s = (self_t *)self;
    uint32_t i;
    for (i = 0; i < count; i++) s->sum += s->kF * v[i];
}

static void source(void *self, tb_real *q, uint32_t n, tb_real inv)
{
    self_t *s = (self_t *)self;
    uint32_t i;
    for (i = n - s->k; i < n; i++) q[i] += s->sum * inv * ((tb_real)1 / (tb_real)s->k);
    s->sum = 0;
}

const tbi_effect tbi_effect_free_end_bearing_heat = {
    .code = 5, .n_params = 2, .self_bytes = sizeof(self_t), .validate = validate, .init = init, .fine = fine,
    .source = source,
};
