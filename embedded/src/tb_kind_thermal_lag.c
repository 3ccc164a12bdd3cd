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
 * input), a0 R, b0 R, wA[NI x NT] R, then with P: wB[NI x NT] R. R: a float32 (hi, lo) pair.
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
    uint32_t NT = m->dims[2], i, src, ch;
    (void)version;
    if (!tbi_parse_lag_head(c, m, &src, &ch)) return;
    m->off[O_A] = c->pos; /* taus */
    for (i = 0; i < NT && !c->err; i++) tbi_take_pair(c, 0, TB_R(1e9), 0);
    tbi_parse_lag_weights(c, m, NT, src, ch);
}

/* THERMAL_LAG's and LINEAR_HISTORY's dims [S, NI, NW, P, U] checked, the sensor and geometric blocks and
 * the body's head: u_source (*src), u_channel (*ch), u_scale; 0 on an error (c->err set) */
int tbi_parse_lag_head(tbi_cur *c, tb_model *m, uint32_t *src, uint32_t *ch)
{
    uint32_t *d = m->dims, S = d[0], NI = d[1], NW = d[2], P = d[3], U = d[4];
    if (S > TB_MAX_SENSORS || NI < 1 || NI > TB_MAX_SENSORS + 1 || NW < 1 || NW > TB_MAX_LAG_TAUS || P > 1 || U > 1) {
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
 * or delays): the input codes, a0, b0, wA and with position terms wB (offsets O_B..O_E), and the
 * operating input's source src and channel ch checked (dims [S, NI, NW, P, U] as both kinds') */
void tbi_parse_lag_weights(tbi_cur *c, tb_model *m, uint32_t NW, uint32_t src, uint32_t ch)
{
    uint32_t S = m->dims[0], NI = m->dims[1], P = m->dims[3], U = m->dims[4], i;
    m->off[O_B] = c->pos; /* input codes */
    for (i = 0; i < NI && !c->err; i++) tbi_take_int(c, 0, U ? S : (S ? S - 1 : 0));
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
    for (i = 0; i < NI; i++) {
        uint32_t code = (uint32_t)PV(m, m->off[O_B] + i);
        tb_real u = code < S ? dT[code] : mo->op_u / u_scale;
        for (k = 0; k < NT; k++) {
            tb_real tau = PR(m, m->off[O_A] + 2u * k), *y = &r->y[i * NT + k];
            if (tau <= 0) {
                *y = u;
            } else if (r->started) {
                tb_real a = tbm_exp(-dt / tau);
                *y = a * *y + (1 - a) * u;
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
    .kind = TB_KIND_THERMAL_LAG, .max_version = 1, .pipeline = 1, .parse = parse, .carve = carve, .check = check,
    .op_input = op_input, .sample = sample, .predict = predict,
};
