/*
 * tb_fx_fixed_fixed_constraint.c - effect fixed_fixed_constraint
 * (thermbench.sim.effects.FixedFixedConstraint, code 6; seed 004): both ends held, a fraction
 * kappa of the free elongation is suppressed by a uniform strain, u(x) -= kappa (x / L) u(L).
 * Section: kappa.
 */
#include "tb_physics.h"

typedef struct {
    tb_real kappa;
} self_t;

static void init(void *self, const tb_model *m, uint32_t at, const tbi_phys_par *c)
{
    (void)c;
    ((self_t *)self)->kappa = PV(m, at);
}

static void elongation(const void *self, tb_real *u, uint32_t n)
{
    tb_real end = u[n], kappa = ((const self_t *)self)->kappa;
    uint32_t i;
    for (i = 0; i <= n; i++) u[i] -= kappa * end * ((tb_real)i / (tb_real)n);
}

const tbi_effect tbi_effect_fixed_fixed_constraint = {
    .code = 6, .n_params = 1, .self_bytes = sizeof(self_t), .init = init, .elongation = elongation,
};
