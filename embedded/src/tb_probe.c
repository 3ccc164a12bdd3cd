/*
 * tb_probe.c - online updates from probe readings: the bias + gain Kalman filter of
 * thermbench/bench/adapt.py (ProbeFilter), in the runtime's precision, allocation-free.
 *
 *   measured = (1 + gain) * predicted + bias + v,   v ~ N(0, r_um2)
 *   between probes bias and gain walk at random: q_bias_um2_per_h, q_gain_per_h per hour
 *
 * The state stands between probes (a random walk has no drift); only its covariance grows with
 * the time since the state's time, so a correction at t is a pure function of the state and t.
 * The update is the Joseph form, as the Python filter's, so the two agree to rounding.
 */
#include "tb_internal.h"

static int finite_params(const tb_probe_params *p)
{
    return isfinite(p->q_bias_um2_per_h) && isfinite(p->q_gain_per_h) && isfinite(p->r_um2) && isfinite(p->bias0_um) &&
           isfinite(p->gain0) && p->q_bias_um2_per_h >= 0 && p->q_gain_per_h >= 0 && p->r_um2 > 0 && p->bias0_um >= 0 &&
           p->gain0 >= 0;
}

int tb_probe_init(tb_probe_state *f, const tb_probe_params *p, tb_real t0_s)
{
    if (!f || !p || !finite_params(p) || !isfinite(t0_s)) return TB_E_ARG;
    memset(f, 0, sizeof *f);
    f->p = *p;
    f->P00 = p->bias0_um * p->bias0_um;
    f->P11 = p->gain0 * p->gain0;
    f->t_s = t0_s;
    return TB_OK;
}

/* the covariance at t (the state's, plus the random walk since its time) */
static void cov_at(const tb_probe_state *f, tb_real t_s, tb_real *P00, tb_real *P01, tb_real *P11)
{
    tb_real dt_h = (t_s - f->t_s) / TB_R(3600.0);
    if (dt_h < 0) dt_h = 0;
    *P00 = f->P00 + f->p.q_bias_um2_per_h * dt_h;
    *P01 = f->P01;
    *P11 = f->P11 + f->p.q_gain_per_h * dt_h;
}

int tb_probe_correct(const tb_probe_state *f, tb_real t_s, tb_real predicted_um, tb_real *corrected_um, tb_real *var_um2)
{
    tb_real P00, P01, P11;
    if (!f || !isfinite(t_s) || !isfinite(predicted_um)) return TB_E_ARG;
    cov_at(f, t_s, &P00, &P01, &P11);
    if (corrected_um) *corrected_um = predicted_um * (1 + f->gain) + f->bias_um;
    if (var_um2) *var_um2 = P00 + TB_R(2.0) * predicted_um * P01 + predicted_um * predicted_um * P11; /* H P H', H = [1, p] */
    return TB_OK;
}

int tb_probe_update(tb_probe_state *f, tb_real t_s, tb_real predicted_um, tb_real measured_um, tb_real *innovation_um)
{
    tb_real P00, P01, P11, h = predicted_um, S, K0, K1, e, r;
    tb_real A00, A01, A10, A11, Q00, Q01, Q11;
    if (!f || !isfinite(t_s) || !isfinite(predicted_um) || !isfinite(measured_um)) return TB_E_ARG;
    if (t_s < f->t_s) return TB_E_LATE; /* a probe older than the state */
    cov_at(f, t_s, &P00, &P01, &P11);
    r = f->p.r_um2;
    e = measured_um - (predicted_um * (1 + f->gain) + f->bias_um);
    S = P00 + TB_R(2.0) * h * P01 + h * h * P11 + r;
    K0 = (P00 + h * P01) / S; /* K = P H' / S */
    K1 = (P01 + h * P11) / S;
    f->bias_um += K0 * e;
    f->gain += K1 * e;
    /* Joseph form: (I - K H) P (I - K H)' + r K K' */
    A00 = 1 - K0; A01 = -K0 * h;
    A10 = -K1;    A11 = 1 - K1 * h;
    Q00 = A00 * (A00 * P00 + A01 * P01) + A01 * (A00 * P01 + A01 * P11);
    Q01 = A10 * (A00 * P00 + A01 * P01) + A11 * (A00 * P01 + A01 * P11);
    Q11 = A10 * (A10 * P00 + A11 * P01) + A11 * (A10 * P01 + A11 * P11);
    f->P00 = Q00 + r * K0 * K0;
    f->P01 = Q01 + r * K0 * K1;
    f->P11 = Q11 + r * K1 * K1;
    f->t_s = t_s;
    f->n_probes++;
    if (innovation_um) *innovation_um = e;
    return isfinite(f->bias_um) && isfinite(f->gain) ? TB_OK : TB_E_INPUT;
}

int tb_probe(const tb_model *m, tb_probe_state *f, tb_real t_s, tb_real axis_mm, tb_real measured_um)
{
    tb_real total = 0;
    int rc = tb_model_predict(m, t_s, axis_mm, 0, &total);
    if (rc != TB_OK) return rc;
    return tb_probe_update(f, t_s, total, measured_um, 0);
}
