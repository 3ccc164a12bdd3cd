/*
 * tb_fx_motor_heat.c - effect motor_heat (thermbench.sim.effects.MotorHeat, code 4): motor heat
 * enters the fixed end (slice 0) through the coupling, Q_M = k_motor lag_tau(v), the lag exact
 * per fine step (y <- a y + (1 - a) v, a = exp(-dt / tau)). Section: k_motor_W_per_mm_min,
 * tau_s (> 0).
 */
#include "tb_physics.h"

typedef struct {
    tb_real k, a; /* gain; lag factor per fine step */
    tb_real y, sum; /* the lagged speed; sum of the power over the macro step */
} self_t;

static int validate(const tb_model *m, uint32_t at) { return PV(m, at + 1) > 0 ? TB_OK : TB_E_PAYLOAD; }

static void init(void *self, const tb_model *m, uint32_t at, const tbi_phys_par *c)
{
    self_t *s = (self_t *)self;
    s->k = PV(m, at);
    s->a = tbm_exp(-c->dt / PV(m, at + 1));
}

static void fine(void *self, const tb_real *v, uint32_t count)
{
    self_t *s = (self_t *)self;
    tb_real sum = s->sum, y = s->y;
    uint32_t i;
    for (i = 0; i < count; i++) { /* the power of the step from the lag's value at its start */
        sum += s->k * y;
        y = s->a * y + (1 - s->a) * v[i];
    }
    s->sum = sum;
    s->y = y;
}

static void source(void *self, tb_real *q, uint32_t n, tb_real inv)
{
    self_t *s = (self_t *)self;
    (void)n;
    q[0] += s->sum * inv;
    s->sum = 0;
}

const tbi_effect tbi_effect_motor_heat = {
    .code = 4, .n_params = 2, .self_bytes = sizeof(self_t), .validate = validate, .init = init, .fine = fine,
    .source = source,
};
