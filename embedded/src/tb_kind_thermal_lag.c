/*
 * tb_kind_thermal_lag.c - kind THERMAL_LAG: the error as weighted first-order lags of the inputs
 * (thermbench/models/thermal_lag.py). Each input (a sensor's rise dT, or the operating input over
 * its scale) is filtered at each time constant tau from 0 at the run's first sample:
 * y_k = a y_{k-1} + (1 - a) u_k, a = exp(-(t_k - t_{k-1}) / tau); tau 0 is the input itself.
 * The error at (t, x) is A(t) + x B(t), A = a0 + sum wA y, B = b0 + sum wB y, the lags
 * interpolated linearly in time between samples (numpy.interp over the log, as thermbench).
 * dims [S, NI, NT, P, U]: sensors in the block, inputs, time constants, position terms (0/1),
 * operating input (0/1); body: u_source (0 feed, 1 axis, 2 load, 3 an input channel), u_channel,
 * u_scale R (> 0), tau[NT] R (>= 0), input codes[NI] (a sensor index < S, or S: the operating
 * input, or from version 2 S + 1 + k: the start state of sensor k), a0 R, b0 R, wA[NI x NT] R, then
 * with P: wB[NI x NT] R; version 2 then the start state's reference: a sensor index < S, or S: the
 * mean of the block's sensors. R: a float32 (hi, lo) pair.
 * The start state of sensor k (thermbench.models.thermal_lag.start_state): its first value above
 * the reference's first value, T0[k] - T0[ref], an input held from the first sample, lagged as the
 * others (its tau-0 weight is 0: the readings count from the run's first).
 */
#include "tb_internal.h"

typedef struct {
    int started;
    tb_real t_last;
    tb_real *y; /* NI x NT lag states */
    tbi_abring ring; /* A and B at the last samples */
} tl_t;

static void parse(tbi_cur *c, tb_model *m, uint16_t version)
{
    uint32_t NT = m->dims[2], S = m->dims[0], i, src, ch;
    if (!tbi_parse_lag_head(c, m, &src, &ch)) return;
    m->off[O_A] = c->pos; /* taus */
    for (i = 0; i < NT && !c->err; i++) tbi_take_pair(c, 0, TB_R(1e9), 0);
    tbi_parse_lag_weights(c, m, NT, src, ch, version >= 2);
    if (c->err) return;
    m->off[O_F] = 0;
    if (version >= 2) { /* the start state's reference */
        m->off[O_F] = c->pos;
        tbi_take_int(c, 0, S);
    }
}

/* the start state's reference: the reference sensor's first value, or the block's mean first value */
static tb_real start_ref(const tb_model *m, const tb_real *T0)
{
    uint32_t S = m->dims[0], r = (uint32_t)PV(m, m->off[O_F]), j;
    tb_real sum = 0;
    if (r < S) return T0[r];
    for (j = 0; j < S; j++) sum += T0[j];
    return S ? sum / (tb_real)S : 0;
}

/* THERMAL_LAG's and LINEAR_HISTORY's dims [S, NI, NW, P, U] checked (NI up to two inputs a sensor, its
 * rise and its start state, and the operating input), the sensor and geometric blocks and the body's
 * head: u_source (*src), u_channel (*ch), u_scale; 0 on an error (c->err set) */
int tbi_parse_lag_head(tbi_cur *c, tb_model *m, uint32_t *src, uint32_t *ch)
{
    uint32_t *d = m->dims, S = d[0], NI = d[1], NW = d[2], P = d[3], U = d[4];
    if (S > TB_MAX_SENSORS || NI < 1 || NI > 2u * TB_MAX_SENSORS + 1u || NW < 1 || NW > TB_MAX_LAG_TAUS || P > 1 || U > 1) {
        c->err = TB_E_DIMS;
        return 0;
    }
    tbi_parse_sensors(c, m, S);
    tbi_parse_geom(c, m);
    m->off[O_BODY] = c->pos;
    *src = tbi_take_int(c, 0, 3);                 /* u_source */
    *ch = tbi_take_int(c, 0, 4u * TB_MAX_SENSORS); /* u_channel */
    tbi_take_pair(c, 0, TB_R(1e30), 1);           /* u_scale > 0 */
    return !c->err;
}

/* THERMAL_LAG's and LINEAR_HISTORY's body after their per-input columns (NW of them: time constants
 * or delays): the input codes (a sensor < S, S the operating input with U, with starts S + 1 + k the
 * start state of sensor k), a0, b0, wA and with position terms wB (offsets O_B..O_E), and the
 * operating input's source src and channel ch checked (dims [S, NI, NW, P, U] as both kinds') */
void tbi_parse_lag_weights(tbi_cur *c, tb_model *m, uint32_t NW, uint32_t src, uint32_t ch, int starts)
{
    uint32_t S = m->dims[0], NI = m->dims[1], P = m->dims[3], U = m->dims[4], i;
    m->off[O_B] = c->pos; /* input codes */
    for (i = 0; i < NI && !c->err; i++) {
        uint32_t code = tbi_take_int(c, 0, starts ? 2u * S : (U ? S : (S ? S - 1 : 0)));
        if (!c->err && code == S && !U) c->err = TB_E_PAYLOAD; /* the operating input's code, with none */
    }
    if (!U && S == 0) c->err = TB_E_DIMS; /* no input at all */
    m->off[O_C] = tbi_take(c, 4);          /* a0, b0 */
    m->off[O_D] = tbi_take(c, 2 * NI * NW); /* wA */
    m->off[O_E] = tbi_take(c, P ? 2 * NI * NW : 0); /* wB */
    if (c->err) return;
    if ((src != 3 || !U) && ch != 0) c->err = TB_E_PAYLOAD;
    if (U && src == 3) {
        for (i = 0; i < S; i++) /* a temperature channel read as the operating input */
            if ((uint32_t)PV(m, m->off[O_SENS] + i) == ch) c->err = TB_E_PAYLOAD;
        if (ch + 1u > m->max_channel) m->max_channel = ch + 1u;
    }
}

static void carve(const tb_model *m, tbi_arena *a, void **ks)
{
    uint32_t n = m->dims[1] * m->dims[2];
    tl_t *r = (tl_t *)tbi_carve(a, sizeof(tl_t));
    tb_real *y = (tb_real *)tbi_carve(a, sizeof(tb_real) * n);
    if (a->p && !a->err) {
        memset(r, 0, sizeof *r);
        memset(y, 0, sizeof(tb_real) * n);
        r->y = y;
    }
    *ks = r;
}

static tb_real op_input(const tb_model *m, const tb_sample *s)
{
    uint32_t b = m->off[O_BODY];
    if (!m->dims[4]) return 0;
    switch ((uint32_t)PV(m, b)) {
    case 0: return s->feed_mm_min;
    case 1: return s->axis_mm;
    case 2: return s->load_N;
    default: return s->temps_C[(uint32_t)PV(m, b + 1u)];
    }
}

static int check(const tb_model *m, const void *ks, const tb_sample *s)
{
    tb_real u = op_input(m, s);
    (void)ks;
    return isfinite(u) && tbm_fabs(u) <= TB_MAX_OPERATING ? TB_OK : TB_E_INPUT;
}

static void sample(const tb_model *m, void *ks, const tbi_motion *mo, const tb_real *dT)
{
    tl_t *r = (tl_t *)ks;
    uint32_t NI = m->dims[1], NT = m->dims[2], S = m->dims[0], i, k;
    tb_real u_scale = PR(m, m->off[O_BODY] + 2u), A = PR(m, m->off[O_C]), B = PR(m, m->off[O_C] + 2u);
    tb_real dt = r->started ? mo->t_s - r->t_last : 0;
    tb_real ref = m->off[O_F] ? start_ref(m, mo->T0) : 0, a[TB_MAX_LAG_TAUS];
    for (k = 0; k < NT; k++) { /* each time constant's decay over this interval, once for every input */
        tb_real tau = PR(m, m->off[O_A] + 2u * k);
        a[k] = tau > 0 && r->started ? tbm_exp(-dt / tau) : 0;
    }
    for (i = 0; i < NI; i++) {
        uint32_t code = (uint32_t)PV(m, m->off[O_B] + i);
        tb_real u = code < S ? dT[code] : code == S ? mo->op_u / u_scale : mo->T0[code - S - 1u] - ref;
        for (k = 0; k < NT; k++) {
            tb_real tau = PR(m, m->off[O_A] + 2u * k), *y = &r->y[i * NT + k];
            if (tau <= 0) {
                *y = u;
            } else if (r->started) {
                *y = a[k] * *y + (1 - a[k]) * u;
            } /* the first sample: 0 (the machine had not started) */
            A += PR(m, m->off[O_D] + 2u * (i * NT + k)) * *y;
            if (m->dims[3]) B += PR(m, m->off[O_E] + 2u * (i * NT + k)) * *y;
        }
    }
    r->started = 1;
    r->t_last = mo->t_s;
    tbi_ab_push(&r->ring, mo->t_s, A, B);
}

static int predict(const tb_model *m, const void *ks, tb_real t, tb_real axis_mm, tb_real *thermal)
{
    return tbi_ab_at(&((const tl_t *)ks)->ring, t, axis_mm, (int)m->dims[3], thermal);
}

const tbi_kind tbi_kind_thermal_lag = {
    .kind = TB_KIND_THERMAL_LAG, .max_version = 2, .pipeline = 1, .parse = parse, .carve = carve, .check = check,
    .op_input = op_input, .sample = sample, .predict = predict,
};
