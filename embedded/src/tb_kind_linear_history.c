/*
 * tb_kind_linear_history.c - kind LINEAR_HISTORY: the error as weighted rises now and some delays
 * earlier (thermbench/models/linear_history.py). Each input (a sensor's rise dT, or the operating input
 * over its scale) goes into a delay line of step h from the run's first sample t0: the line holds
 * v_m = u(t0 + m h), linear between the two samples around that time; the input d seconds earlier
 * is linear between the line's values, the first sample's value before t0 (numpy.interp, as
 * thermbench.models.linear_history.delay_line); a delay of 0 is the input itself. The error at (t, x)
 * is A(t) + x B(t), A = a0 + sum wA y, B = b0 + sum wB y, interpolated linearly between samples.
 * dims [S, NI, ND, P, U, C]: sensors in the block, inputs, delays, position terms (0/1), operating
 * input (0/1), the line's length per input (at least floor(longest delay / h) + 3); body: u_source
 * (0 feed, 1 axis, 2 load, 3 an input channel), u_channel, u_scale R (> 0), h R (> 0), delay[ND] R
 * (0, or >= h), input codes[NI] (a sensor index < S, or S: the operating input), a0 R, b0 R,
 * wA[NI x ND] R, then with P: wB[NI x ND] R. R: a float32 (hi, lo) pair. The body starts as
 * THERMAL_LAG's: its operating input and its check serve here too.
 */
#include "tb_internal.h"

extern const tbi_kind tbi_kind_thermal_lag;

typedef struct {
    int started;
    tb_real t0, t_prev;
    uint32_t n_grid;   /* grid values pushed so far: v_0 .. v_{n_grid - 1} */
    tb_real *u_first;  /* NI: each input at the first sample (its value before t0) */
    tb_real *u_prev;   /* NI: each input at the previous sample */
    tb_real *line;     /* NI x C: v_m at slot m % C */
    tbi_abring ring;   /* A and B at the last samples */
} lh_t;

static void parse(tbi_cur *c, tb_model *m, uint16_t version)
{
    uint32_t ND = m->dims[2], C = m->dims[5], i, src, ch;
    tb_real h, dmax = 0;
    (void)version;
    if (C < 3 || C > TB_MAX_DELAY_LINE) {
        c->err = TB_E_DIMS;
        return;
    }
    if (m->dims[1] > TB_MAX_SENSORS + 1u) { /* one input a sensor and the operating input */
        c->err = TB_E_DIMS;
        return;
    }
    if (!tbi_parse_lag_head(c, m, &src, &ch)) return;
    m->off[O_F] = c->pos;
    h = tbi_take_pair(c, 0, TB_R(1e9), 1); /* the line's step > 0 */
    m->off[O_A] = c->pos;                  /* delays */
    for (i = 0; i < ND && !c->err; i++) {
        tb_real dl = tbi_take_pair(c, 0, TB_R(1e9), 0);
        if (dl > 0 && dl < h) c->err = TB_E_PAYLOAD; /* a delay shorter than the step is not in the line */
        if (dl > dmax) dmax = dl;
    }
    if (!c->err && (tb_real)C < dmax / h + 3) c->err = TB_E_DIMS; /* the line cannot hold the longest delay */
    tbi_parse_lag_weights(c, m, ND, src, ch, 0);
}

static void carve(const tb_model *m, tbi_arena *a, void **ks)
{
    uint32_t NI = m->dims[1], C = m->dims[5];
    lh_t *r = (lh_t *)tbi_carve(a, sizeof(lh_t));
    tb_real *first = (tb_real *)tbi_carve(a, sizeof(tb_real) * NI);
    tb_real *prev = (tb_real *)tbi_carve(a, sizeof(tb_real) * NI);
    tb_real *line = (tb_real *)tbi_carve(a, sizeof(tb_real) * NI * C);
    if (a->p && !a->err) {
        memset(r, 0, sizeof *r);
        r->u_first = first;
        r->u_prev = prev;
        r->line = line;
    }
    *ks = r;
}

static void sample(const tb_model *m, void *ks, const tbi_motion *mo, const tb_real *dT)
{
    lh_t *r = (lh_t *)ks;
    uint32_t S = m->dims[0], NI = m->dims[1], ND = m->dims[2], C = m->dims[5], i, k;
    tb_real u_scale = PR(m, m->off[O_BODY] + 2u), h = PR(m, m->off[O_F]);
    tb_real A = PR(m, m->off[O_C]), B = PR(m, m->off[O_C] + 2u), t = mo->t_s, g, u[TB_MAX_SENSORS + 1u];
    for (i = 0; i < NI; i++) { /* each input at this sample, once */
        uint32_t code = (uint32_t)PV(m, m->off[O_B] + i);
        u[i] = code < S ? dT[code] : mo->op_u / u_scale;
    }
    if (!r->started) {
        r->t0 = t;
        r->n_grid = 1u;
    } else { /* the grid times this sample passed: v_m between the previous sample and this one */
        while ((g = r->t0 + (tb_real)r->n_grid * h) <= t) {
            for (i = 0; i < NI; i++) r->line[i * C + r->n_grid % C] = tbi_interp1(g, r->t_prev, t, r->u_prev[i], u[i]);
            r->n_grid++;
        }
    }
    for (i = 0; i < NI; i++) {
        if (!r->started) {
            r->u_first[i] = u[i];
            r->line[i * C] = u[i]; /* v_0 */
        }
        r->u_prev[i] = u[i];
        for (k = 0; k < ND; k++) {
            tb_real dl = PR(m, m->off[O_A] + 2u * k), y = u[i], q = t - dl;
            if (dl > 0) {
                if (q <= r->t0) {
                    y = r->u_first[i];
                } else { /* between v_j and v_{j+1}: both in the line (dl >= h, and C covers the longest) */
                    tb_real x = (q - r->t0) / h;
                    uint32_t j = (uint32_t)tbi_floor_clamp(x, 0, (tbi_int)r->n_grid - 2);
                    tb_real v0 = r->line[i * C + j % C], v1 = r->line[i * C + (j + 1u) % C];
                    y = v0 + (q - (r->t0 + (tb_real)j * h)) * ((v1 - v0) / h);
                }
            }
            A += PR(m, m->off[O_D] + 2u * (i * ND + k)) * y;
            if (m->dims[3]) B += PR(m, m->off[O_E] + 2u * (i * ND + k)) * y;
        }
    }
    r->started = 1;
    r->t_prev = t;
    tbi_ab_push(&r->ring, t, A, B);
}

static int predict(const tb_model *m, const void *ks, tb_real t, tb_real axis_mm, tb_real *thermal)
{
    return tbi_ab_at(&((const lh_t *)ks)->ring, t, axis_mm, (int)m->dims[3], thermal);
}

static int check(const tb_model *m, const void *ks, const tb_sample *s)
{
    return tbi_kind_thermal_lag.check(m, ks, s);
}

static tb_real op_input(const tb_model *m, const tb_sample *s)
{
    return tbi_kind_thermal_lag.op_input(m, s);
}

const tbi_kind tbi_kind_linear_history = {
    .kind = TB_KIND_LINEAR_HISTORY, .max_version = 1, .pipeline = 1, .parse = parse, .carve = carve, .check = check,
    .op_input = op_input, .sample = sample, .predict = predict,
};
