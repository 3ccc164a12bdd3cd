/*
 * tb_fx_quadratic_friction_heat.c - effect quadratic_friction_heat
 * (thermbench.sim.effects.QuadraticFrictionHeat, code 2): the nut's friction heat has a viscous
 * part, QN = k4 v + k5 v^2. Section: k5_W_per_mm_min2.
 */
#include "tb_physics.h"

typedef struct {
    tb_real k5;
} self_t;

static void init(void *self, const tb_model *m, uint32_t at, const tbi_phys_par *c)
{
    (void)c;
    ((self_t *)self)->k5 = PV(m, at);
}

static void nut_heat(const void *self, const tb_real *v, const tb_real *load, tb_real *qn, uint32_t count)
{
    tb_real k5 = ((const self_t *)self)->k5;
    uint32_t i;
    (void)load;
    for (i = 0; i < count; i++) qn[i] += k5 * v[i] * v[i];
}

const tbi_effect tbi_effect_quadratic_friction_heat = {
    .code = 2, .n_params = 1, .self_bytes = sizeof(self_t), .init = init, .nut_heat = nut_heat,
};
