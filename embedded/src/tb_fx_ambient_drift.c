/*
 * tb_fx_ambient_drift.c - effect ambient_drift (thermbench.sim.effects.AmbientDrift, code 1):
 * without an ambient sensor the screw convects to Ta(t) = Ta0 + amplitude (sin(w (t + phase))
 * - sin(w phase)) + rate t, w = 2 pi / period, t from the run's first sample (with a sensor the
 * measured ambient is used, as in thermbench). The axis growth alpha dTa x is the core's.
 * Section: amplitude_C, period_s (> 0 without a sensor), phase_s, rate_C_per_h.
 */
#include "tb_physics.h"

typedef struct {
    tb_real amp, w, ph, sin_ph, rate;
} self_t;

static int validate(const tb_model *m, uint32_t at)
{
    return m->dims[0] == 0 && !(PV(m, at + 1) > 0) ? TB_E_PAYLOAD : TB_OK;
}

static void init(void *self, const tb_model *m, uint32_t at, const tbi_phys_par *c)
{
    self_t *s = (self_t *)self;
    (void)c;
    s->amp = PV(m, at);
    s->w = TB_R(2.0 * 3.14159265358979323846) / PV(m, at + 1);
    s->ph = PV(m, at + 2);
    s->sin_ph = tbm_sin(s->w * s->ph);
    s->rate = PV(m, at + 3);
}

static tb_real ambient_rise(const void *self, tb_real tt)
{
    const self_t *s = (const self_t *)self;
    return s->amp * (tbm_sin(s->w * (tt + s->ph)) - s->sin_ph) + s->rate * tt / TB_R(3600.0);
}

const tbi_effect tbi_effect_ambient_drift = {
    .code = 1, .n_params = 4, .self_bytes = sizeof(self_t), .validate = validate, .init = init,
    .ambient_rise = ambient_rise,
};
