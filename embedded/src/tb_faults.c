/*
 * tb_faults.c - sensor faults at the compensator: each temperature checked sample by sample, a
 * faulty one read as the other sensors predict it, the correction bounded in value and rate; as
 * thermbench/bench/faults.py (FaultMonitor, Bounds) does it. Allocation-free.
 *
 * Per sensor i, with rise = T - T0 (T0 the sensor's reading at the run's first sample), rate = (T - e) 3600 / tau
 * (e the exponential average e += (1 - exp(-dt / tau)) (T - e), K/h), the rules in this order (the
 * first that fires names the fault, which is latched until tb_faults_reset):
 *   open    T not finite or outside [plausible_lo_C, plausible_hi_C]
 *   range   rise beyond [rise_lo - m, rise_hi + m], m = max(rise_hi - rise_lo, range_min_K)
 *   rate    |rate| > rate_factor * rate_max + rate_min_K_h
 *   stuck   T unchanged for longer than max(stuck_factor * flat_s, stuck_min_s) while the others'
 *           prediction of its rise moved by more than stuck_move_K since it last changed (flat_s < 0:
 *           never judged stuck; tol_K < 0: judged on the time alone)
 *   others  |rise - (icpt + coef @ rise)| > tol_K or |rate - coef @ rate| > rate_tol_K_h for a
 *           healthy sensor: the one sensor whose reconstruction (rise and rate) leaves the smallest
 *           sum of squared departures (each over its tolerance) of the other healthy sensors is
 *           judged (Dunia, Qin, Edgar and McAvoy, AIChE J. 42(10), 1996)
 * A faulty sensor's rise is reconstructed from the start of its last trusted reading by the lines
 * icpt + coef @ rise (the faulty ones among the others as reconstructed: 3 passes when more than one
 * is faulty), and the model reads T0 + that rise; a sensor no other predicts (tol_K < 0) is held at
 * its last trusted reading; its rate as coef @ rate by the same passes (0 when no other predicts
 * it). A sensor not plausible at the run's first sample starts at the
 * plausible sensors' mean (unknown_start_C when none is) plus its start_offset_K.
 *
 * Bounds (tb_faults_bound): |value| <= max_um (max_um < 0: none), then the change since the previous
 * bounded value of the same series at most rate_um_s per second (rate_um_s < 0: none). A value that
 * is not finite passes as it is and leaves the series' state alone.
 *
 * The faults file (written by the export, thermbench/export/faultfile.py, kind TB_KIND_FAULTS) has
 * the model file's header and CRC; dims = [n]; payload: the TBF_SCALARS scalars below, then the
 * arrays rise_lo_K, rise_hi_K, rate_max_K_h, flat_s, tol_K, start_offset_K, icpt, rate_tol_K_h
 * (n each; tol_K, rate_tol_K_h < 0: no such line), then coef (n x n, row i the line of sensor i, coef[i][i] = 0). The sensors are the model's, in the order
 * of its samples' temps_C. The file is read in place.
 */
#include "tb_internal.h"

enum {
    TBF_TAU = 0,
    TBF_PLAUSIBLE_LO,
    TBF_PLAUSIBLE_HI,
    TBF_UNKNOWN_START,
    TBF_RANGE_MIN,
    TBF_RATE_FACTOR,
    TBF_RATE_MIN,
    TBF_STUCK_FACTOR,
    TBF_STUCK_MIN,
    TBF_STUCK_MOVE,
    TBF_MAX_UM,
    TBF_RATE_UM_S,
    TBF_SCALARS
};
enum { TBF_RISE_LO = 0, TBF_RISE_HI, TBF_RATE_MAX, TBF_FLAT, TBF_TOL, TBF_OFFSET, TBF_ICPT, TBF_RATE_TOL, TBF_ARRAYS };

static tb_real sc(const tb_faults *f, uint32_t k) { return (tb_real)tbi_rd_f32(f->payload + 4u * k); }
static tb_real arr(const tb_faults *f, uint32_t a, uint32_t i)
{
    return (tb_real)tbi_rd_f32(f->payload + 4u * (TBF_SCALARS + a * f->n_sensors + i));
}
static tb_real coef(const tb_faults *f, uint32_t i, uint32_t k)
{
    return (tb_real)tbi_rd_f32(f->payload + 4u * (TBF_SCALARS + TBF_ARRAYS * f->n_sensors + i * f->n_sensors + k));
}

/* icpt[i] + coef[i] @ rise: sensor i's rise as the others predict it */
static tb_real line(const tb_faults *f, uint32_t i, const tb_real *rise)
{
    tb_real p = arr(f, TBF_ICPT, i);
    uint32_t k;
    for (k = 0; k < f->n_sensors; k++) p += coef(f, i, k) * rise[k];
    return p;
}

/* coef[i] @ rate: sensor i's rate as the others' rates predict it */
static tb_real rate_line(const tb_faults *f, uint32_t i, const tb_real *rate)
{
    tb_real p = 0;
    uint32_t k;
    for (k = 0; k < f->n_sensors; k++) p += coef(f, i, k) * rate[k];
    return p;
}

/* sensor k's departures from the others' prediction over their tolerances (0 without a line): rise, rate */
static tb_real dep_rise(const tb_faults *f, uint32_t k, const tb_real *rise)
{
    tb_real tol = arr(f, TBF_TOL, k);
    return tol < 0 ? 0 : (rise[k] - line(f, k, rise)) / tol;
}
static tb_real dep_rate(const tb_faults *f, uint32_t k, const tb_real *rate)
{
    tb_real tol = arr(f, TBF_RATE_TOL, k);
    return tol < 0 ? 0 : (rate[k] - rate_line(f, k, rate)) / tol;
}

int tb_faults_open(tb_faults *f, const uint8_t *file, size_t len)
{
    uint32_t n_payload, n, i, dims[TB_MAX_DIMS];
    uint16_t version, kind;
    int rc;
    if (!f) return TB_E_ARG;
    memset(f, 0, sizeof *f);
    if (!file) return TB_E_ARG;
    if ((rc = tbi_check_file(file, len, &version, &kind, &n_payload)) != TB_OK) return rc;
    if (version != TB_FORMAT_VERSION) return TB_E_VERSION;
    if (kind != TB_KIND_FAULTS) return TB_E_KIND;
    if ((rc = tbi_check_dims(file, dims)) != TB_OK) return rc;
    if (tbi_rd_u16(file + 8) != 1u) return TB_E_DIMS;
    n = dims[0];
    if (n > TB_MAX_SENSORS) return TB_E_DIMS;
    if (n_payload != TBF_SCALARS + TBF_ARRAYS * n + n * n) return TB_E_DIMS;
    if ((rc = tbi_payload_finite(file + TB_HEADER_BYTES, n_payload)) != TB_OK) return rc;
    f->payload = file + TB_HEADER_BYTES;
    f->n_sensors = n;
    rc = TB_OK;
    if (!(sc(f, TBF_TAU) > 0) || !(sc(f, TBF_PLAUSIBLE_LO) < sc(f, TBF_PLAUSIBLE_HI)) || !(sc(f, TBF_RANGE_MIN) >= 0) ||
        !(sc(f, TBF_RATE_FACTOR) >= 0) || !(sc(f, TBF_RATE_MIN) >= 0) || !(sc(f, TBF_STUCK_FACTOR) >= 0) ||
        !(sc(f, TBF_STUCK_MIN) >= 0) || !(sc(f, TBF_STUCK_MOVE) >= 0))
        rc = TB_E_PAYLOAD;
    for (i = 0; i < n && rc == TB_OK; i++) /* rise_lo <= rise_hi, rate_max >= 0, a sensor's line without itself */
        if (!(arr(f, TBF_RISE_LO, i) <= arr(f, TBF_RISE_HI, i)) || !(arr(f, TBF_RATE_MAX, i) >= 0) || coef(f, i, i) != 0 ||
            arr(f, TBF_TOL, i) == 0 || arr(f, TBF_RATE_TOL, i) == 0 || (arr(f, TBF_TOL, i) < 0 && arr(f, TBF_RATE_TOL, i) >= 0))
            rc = TB_E_PAYLOAD; /* a tolerance is > 0 or none (< 0); a rate line only where there is a rise line */
    if (rc != TB_OK) {
        memset(f, 0, sizeof *f); /* a refused file checks nothing (tb_faults_step: TB_E_ARG) */
        return rc;
    }
    f->tau_s = sc(f, TBF_TAU);
    f->max_um = sc(f, TBF_MAX_UM);
    f->rate_um_s = sc(f, TBF_RATE_UM_S);
    return TB_OK;
}

void tb_faults_reset(tb_faults *f)
{
    if (!f) return;
    f->started = 0;
    f->faulty = 0;
    f->trusted = 0;
    memset(f->fault, 0, sizeof f->fault);
}

/* the faulty sensors' rises in v (in place), from their last trusted rise, by the lines; rates: their
 * rates instead, from 0, by the lines without their intercept (0 where no other predicts it) */
static void reconstruct(const tb_faults *f, tb_real *v, int rates)
{
    uint32_t i, pass, n = f->n_sensors, n_bad = 0;
    for (i = 0; i < n; i++)
        if (f->fault[i]) {
            v[i] = !rates && ((f->trusted >> i) & 1u) ? f->trusted_C[i] - f->T0_C[i] : 0;
            n_bad++;
        }
    if (!n_bad) return;
    for (pass = 0; pass < (n_bad > 1 ? 3u : 1u); pass++)
        for (i = 0; i < n; i++)
            if (f->fault[i] && arr(f, TBF_TOL, i) >= 0) v[i] = rates ? rate_line(f, i, v) : line(f, i, v);
}

static int plausible(const tb_faults *f, tb_real T)
{
    return isfinite(T) && T >= sc(f, TBF_PLAUSIBLE_LO) && T <= sc(f, TBF_PLAUSIBLE_HI);
}

int tb_faults_step(tb_faults *f, const tb_sample *s, tb_real *temps_C)
{
    uint32_t i, j, k, n;
    tb_real t, known[TB_MAX_SENSORS], used[TB_MAX_SENSORS], pred[TB_MAX_SENSORS], rates[TB_MAX_SENSORS], worst = 0;
    uint32_t changed = 0, ok = 0;
    if (!f || !f->payload || !s || !temps_C) return TB_E_ARG;
    n = f->n_sensors;
    t = s->t_s;
    if (!isfinite(t) || s->n_temps < n || (n && !s->temps_C)) return TB_E_INPUT;
    if (f->started && t < f->t_last_s) return TB_E_INPUT;
    for (i = 0; i < n; i++)
        if (plausible(f, s->temps_C[i])) ok |= 1u << i;
    if (!f->started) {
        tb_real ref = 0;
        uint32_t m = 0;
        for (i = 0; i < n; i++)
            if ((ok >> i) & 1u) {
                ref += s->temps_C[i];
                m++;
            }
        ref = m ? ref / (tb_real)m : sc(f, TBF_UNKNOWN_START);
        for (i = 0; i < n; i++) { /* faulty from the first sample: where the others put it */
            f->T0_C[i] = f->e_C[i] = (ok >> i) & 1u ? s->temps_C[i] : ref + arr(f, TBF_OFFSET, i);
            f->changed_s[i] = t;
        }
        changed = ~0u;
    } else {
        tb_real a = t > f->t_last_s ? 1 - tbm_exp(-(t - f->t_last_s) / f->tau_s) : 0;
        for (i = 0; i < n; i++) {
            tb_real T = s->temps_C[i];
            if (((ok >> i) & 1u) && t > f->t_last_s) f->e_C[i] += a * (T - f->e_C[i]);
            if (!(T == f->last_C[i])) {
                changed |= 1u << i;
                f->changed_s[i] = t;
            }
        }
    }
    f->t_last_s = t;
    for (i = 0; i < n; i++) {
        f->last_C[i] = s->temps_C[i];
        known[i] = isfinite(s->temps_C[i]) ? s->temps_C[i] - f->T0_C[i] : 0;
    }
    reconstruct(f, known, 0);
    for (i = 0; i < n; i++) pred[i] = line(f, i, known);
    for (i = 0; i < n; i++)
        if (!f->started || ((changed >> i) & 1u)) f->pac_K[i] = pred[i];
    f->started = 1;
    for (i = 0; i < n; i++) { /* the rules, in order */
        tb_real T = s->temps_C[i], rise = T - f->T0_C[i], rate = (T - f->e_C[i]) * (TB_R(3600.0) / f->tau_s);
        tb_real lo = arr(f, TBF_RISE_LO, i), hi = arr(f, TBF_RISE_HI, i), m = hi - lo, flat = arr(f, TBF_FLAT, i);
        uint8_t why = TB_FAULT_NONE;
        if (f->fault[i]) continue;
        if (m < sc(f, TBF_RANGE_MIN)) m = sc(f, TBF_RANGE_MIN);
        if (!((ok >> i) & 1u)) why = TB_FAULT_OPEN;
        else if (rise > hi + m || rise < lo - m) why = TB_FAULT_RANGE;
        else if (tbm_fabs(rate) > sc(f, TBF_RATE_FACTOR) * arr(f, TBF_RATE_MAX, i) + sc(f, TBF_RATE_MIN)) why = TB_FAULT_RATE;
        else if (flat >= 0) {
            tb_real after = sc(f, TBF_STUCK_FACTOR) * flat;
            if (after < sc(f, TBF_STUCK_MIN)) after = sc(f, TBF_STUCK_MIN);
            if (t - f->changed_s[i] > after && (arr(f, TBF_TOL, i) < 0 || tbm_fabs(pred[i] - f->pac_K[i]) > sc(f, TBF_STUCK_MOVE)))
                why = TB_FAULT_STUCK;
        }
        if (why) {
            f->fault[i] = why;
            f->onset_s[i] = t;
            f->faulty |= 1u << i;
        }
    }
    for (i = 0; i < n; i++) {
        tb_real T = s->temps_C[i];
        used[i] = isfinite(T) ? T - f->T0_C[i] : 0;
        rates[i] = isfinite(T) ? (T - f->e_C[i]) * (TB_R(3600.0) / f->tau_s) : 0;
    }
    reconstruct(f, used, 0);
    reconstruct(f, rates, 1);
    for (i = 0; i < n; i++) { /* the healthy sensors' departures from the others' prediction, over their tolerance */
        tb_real a, b;
        if (f->fault[i]) continue;
        a = tbm_fabs(dep_rise(f, i, used));
        b = tbm_fabs(dep_rate(f, i, rates));
        if (a > worst) worst = a;
        if (b > worst) worst = b;
    }
    if (worst > 1) { /* the sensor whose reconstruction explains the departures best */
        /* read as the others predict it, sensor j moves each other line by coef[k][j] times its change:
         * the others' predictions once (pr, prr), then O(n) per candidate (thermbench/bench/faults.py
         * recomputes them whole: the same sums, in another order) */
        tb_real pr[TB_MAX_SENSORS], prr[TB_MAX_SENSORS], best = 0;
        uint32_t culprit = n;
        for (k = 0; k < n; k++) {
            pr[k] = line(f, k, used);
            prr[k] = rate_line(f, k, rates);
        }
        for (j = 0; j < n; j++) {
            tb_real left = 0, du, dr;
            if (f->fault[j] || arr(f, TBF_TOL, j) < 0) continue;
            du = pr[j] - used[j]; /* its rise and rate, reconstructed, less as read */
            dr = prr[j] - rates[j];
            for (k = 0; k < n; k++)
                if (k != j && !f->fault[k]) {
                    tb_real c = coef(f, k, j), tol = arr(f, TBF_TOL, k), rtol = arr(f, TBF_RATE_TOL, k);
                    tb_real a = tol < 0 ? 0 : (used[k] - pr[k] - c * du) / tol;
                    tb_real b = rtol < 0 ? 0 : (rates[k] - prr[k] - c * dr) / rtol;
                    left += a * a + b * b;
                }
            if (culprit == n || left < best) {
                culprit = j;
                best = left;
            }
        }
        if (culprit < n) { /* always: a departure is of a sensor with a line, itself a candidate */
            f->fault[culprit] = TB_FAULT_OTHERS;
            f->onset_s[culprit] = t;
            f->faulty |= 1u << culprit;
            reconstruct(f, used, 0);
        }
    }
    for (i = 0; i < n; i++) {
        if (!f->fault[i]) {
            f->trusted_C[i] = s->temps_C[i];
            f->trusted |= 1u << i;
            temps_C[i] = s->temps_C[i];
        } else {
            temps_C[i] = f->T0_C[i] + used[i];
        }
    }
    return TB_OK;
}

int tb_faults_bound(const tb_faults *f, tb_bound *b, tb_real t_s, tb_real value_um, tb_real *bounded_um)
{
    tb_real v = value_um;
    int acted = 0;
    if (!f || !f->payload || !b || !bounded_um) return TB_E_ARG;
    if (!isfinite(value_um)) { /* no value: nothing to bound, the series goes on from its last */
        *bounded_um = value_um;
        return 0;
    }
    if (f->max_um >= 0 && tbm_fabs(v) > f->max_um) {
        v = v > 0 ? f->max_um : -f->max_um;
        acted = 1;
    }
    if (!isfinite(t_s)) { /* no time: the value bound only, the series left alone */
        *bounded_um = v;
        return acted;
    }
    if (b->started && f->rate_um_s >= 0) {
        tb_real dt = t_s > b->t_s ? t_s - b->t_s : 0, step = f->rate_um_s * dt;
        if (v < b->value_um - step) {
            v = b->value_um - step;
            acted = 1;
        } else if (v > b->value_um + step) {
            v = b->value_um + step;
            acted = 1;
        }
    }
    b->value_um = v;
    b->t_s = t_s;
    b->started = 1;
    *bounded_um = v;
    return acted;
}
