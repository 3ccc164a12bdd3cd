/*
 * tb_fx_load_dependent_heat.c - effect load_dependent_heat
 * (thermbench.sim.effects.LoadDependentHeat, code 3): the nut's friction heat grows with the
 * axial load F (tb_sample.load_N), QN = (k4 + k6 F) v. Section: k6_W_per_N_mm_min.
 */
#include "tb_physics.h"

typedef struct {
    tb_real k6;
} self_t;

static void init(void *self, const tb_model *m, uint32_t at, const tbi_phys_par *c)
{
    (void)c;
    ((self_t *)self)->k6 = PV(m, at);
}

static void nut_heat(const void *self, const tb_real *v, const tb_real *load, tb_real *qn, uint32_t count)
{
    tb_real k6 = ((const self_t *)self)->k6;
    uint32_t i;
    for (i = 0; i < count; i++) qn[i] += k6 * load[i] * v[i];
}

const tbi_effect tbi_effect_load_dependent_heat = {
    .code = 3, .n_params = 1, .self_bytes = sizeof(self_t), .init = init, .nut_heat = nut_heat,
};
