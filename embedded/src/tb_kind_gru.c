/*
 * tb_kind_gru.c - kind GRU: a PyTorch GRU cell (gates r, z, n) run over the dT history at K
 * lags of step_s, then a linear head giving the curve coefficients of a polynomial in the
 * standardised position. The history is a ring of dT at the sample period (the log must be
 * uniformly sampled; missing samples are filled as numpy.interp would).
 * dims [S, H, D, K]; body: step_s, seq_mean[S], seq_scale[S] (> 0), p_mean, p_scale (> 0),
 * y_mean, y_scale (> 0); O_A W_ih (3H x S), O_B W_hh (3H x H), O_C b_ih, O_D b_hh,
 * O_E head W ((D + 1) x H), O_F head b.
 */
#include "tb_internal.h"

typedef struct { /* ring of dT at the sample period */
    uint32_t cap, n, head;
    tb_real t_new; /* time of the newest sample (as received): positions are counted back from it, so a
                     * float clock far from 0 (its rounding) never moves a lag by a fraction of a period */
    float *ring;    /* cap x S */
} gru_t;

/* y[i] = b[i] + sum_j W[i][j] v[j] for the rows i < H of W (H x n float32 of the payload, row-major):
 * four rows at a time, so each v[j] is loaded once for four multiply-adds */
static void gru_rows(const uint8_t *w, const uint8_t *b, const tb_real *v, uint32_t n, uint32_t H, tb_real *y)
{
    uint32_t i = 0, j;
    for (; i + 4u <= H; i += 4u, w += 16u * n) {
        tb_real s0 = TBI_W(b, i), s1 = TBI_W(b, i + 1u), s2 = TBI_W(b, i + 2u), s3 = TBI_W(b, i + 3u);
        for (j = 0; j < n; j++) {
            tb_real vj = v[j];
            s0 += TBI_W(w, j) * vj;
            s1 += TBI_W(w, n + j) * vj;
            s2 += TBI_W(w, 2u * n + j) * vj;
            s3 += TBI_W(w, 3u * n + j) * vj;
        }
        y[i] = s0;
        y[i + 1u] = s1;
        y[i + 2u] = s2;
        y[i + 3u] = s3;
    }
    for (; i < H; i++, w += 4u * n) y[i] = TBI_W(b, i) + tbi_dot(w, v, n);
}

static void parse(tbi_cur *c, tb_model *m, uint16_t version)
{
    uint32_t *d = m->dims, i, at;
    uint32_t S = d[0], H = d[1], D = d[2], K = d[3];
    (void)version;
    if (S < 1 || S > TB_MAX_SENSORS || H < 1 || H > TB_MAX_GRU_HIDDEN || D > TB_MAX_POLY || K > TB_MAX_LAGS) {
        c->err = TB_E_DIMS;
        return;
    }
    if (!(PV(m, 0) > 0)) { c->err = TB_E_PAYLOAD; return; } /* needs the sample period */
    tbi_parse_sensors(c, m, S);
    tbi_parse_geom(c, m);
    m->off[O_BODY] = c->pos;
    tbi_take_val(c, 1e-3f, 1e7f, 0); /* step_s */
    at = tbi_take(c, 2 * S);
    for (i = 0; i < S && !c->err; i++)
        if (!(PV(m, at + S + i) > 0)) c->err = TB_E_PAYLOAD;
    tbi_take(c, 1);
    tbi_take_val(c, 0, 1e30f, 1); /* p scale */
    tbi_take(c, 1);
    tbi_take_val(c, 0, 1e30f, 1); /* y scale */
    m->off[O_A] = tbi_take(c, 3 * H * S);
    m->off[O_B] = tbi_take(c, 3 * H * H);
    m->off[O_C] = tbi_take(c, 3 * H);
    m->off[O_D] = tbi_take(c, 3 * H);
    m->off[O_E] = tbi_take(c, (D + 1) * H);
    m->off[O_F] = tbi_take(c, D + 1);
    if (!c->err && (tb_real)K * PV(m, m->off[O_BODY]) / PV(m, 0) > (tb_real)TB_MAX_WINDOW)
        c->err = TB_E_DIMS;
    if (!c->err && (K + 1u) * 3u * H * (H + S) > 20000000u) c->err = TB_E_DIMS; /* work per predict */
}

static void carve(const tb_model *m, tbi_arena *a, void **ks)
{
    gru_t *g = (gru_t *)tbi_carve(a, sizeof(gru_t));
    /* the window's samples (+ 4) */
    size_t cap = (size_t)tbm_ceil((tb_real)m->dims[3] * PV(m, m->off[O_BODY]) / PV(m, 0) - TB_R(1e-9)) + 4u;
    float *r = (float *)tbi_carve(a, sizeof(float) * cap * m->dims[0]);
    if (a->p && !a->err) {
        memset(g, 0, sizeof *g);
        g->cap = (uint32_t)cap;
        g->ring = r;
    }
    *ks = g;
}

static void sample(const tb_model *m, void *ks, const tbi_motion *mo, const tb_real *dT)
{
    gru_t *g = (gru_t *)ks;
    tb_real t = mo->t_s;
    uint32_t S = m->dims[0], j;
    tb_real period = PV(m, 0);
    if (g->n > 0) { /* samples missing in between (a dropped or rejected one): the values numpy.interp gives */
        uint32_t newest = (g->head + g->cap - 1) % g->cap, k, d;
        d = (uint32_t)tbi_floor_clamp((t - g->t_new) / period + TB_R(0.5), 1, (tbi_int)g->cap);
        for (k = 1; k < d; k++) {
            tb_real w = (tb_real)k / (tb_real)d;
            for (j = 0; j < S; j++) {
                tb_real v0 = (tb_real)g->ring[newest * S + j];
                g->ring[g->head * S + j] = (float)(v0 + w * (dT[j] - v0));
            }
            g->head = (g->head + 1) % g->cap;
            if (g->n < g->cap) g->n++;
        }
    }
    g->t_new = t;
    for (j = 0; j < S; j++) g->ring[g->head * S + j] = (float)dT[j];
    g->head = (g->head + 1) % g->cap;
    if (g->n < g->cap) g->n++;
}

static int predict(const tb_model *m, const void *ks, tb_real t, tb_real axis_mm, tb_real *thermal)
{
    const gru_t *g = (const gru_t *)ks;
    uint32_t S = m->dims[0], H = m->dims[1], D = m->dims[2], K = m->dims[3], j, i, k;
    uint32_t body = m->off[O_BODY];
    tb_real step = PV(m, body), period = PV(m, 0);
    tb_real h[TB_MAX_GRU_HIDDEN], hn[TB_MAX_GRU_HIDDEN], rr[TB_MAX_GRU_HIDDEN], si[TB_MAX_GRU_HIDDEN], sh[TB_MAX_GRU_HIDDEN];
    tb_real x[TB_MAX_SENSORS];
    uint32_t gate;
    tb_real p, out = 0, pw = 1;
    uint32_t oldest = (g->head + g->cap - g->n) % g->cap;
    if (g->n == 0) return TB_E_NOTREADY;
    for (j = 0; j < H; j++) h[j] = 0;
    for (k = K + 1; k-- > 0;) { /* oldest lag first */
        /* the lag's position in samples from the oldest: (n - 1) less how far it lies behind the newest
         * sample. A lag that falls on a sample to within the rounding of the clock is that sample
         * (numpy.interp at a sample's own time): in float, far from t = 0, t_new - t is the difference
         * of two rounded times (1/64 s apart at 1.5 days), not a whole number of periods */
        tb_real back = ((g->t_new - t) + (tb_real)k * step) / period, whole = tbm_floor(back + TB_R(0.5));
        tb_real pos;
        uint32_t i0, i1;
        tb_real w;
        if (tbm_fabs(back - whole) * period <= TBI_TIME_SLACK(t)) back = whole;
        pos = (tb_real)(g->n - 1) - back;
        if (pos < 0 && g->n == g->cap) return TB_E_LATE;
        if (pos <= 0) { i0 = i1 = 0; w = 0; }
        else if (pos >= (tb_real)(g->n - 1)) { i0 = i1 = g->n - 1; w = 0; }
        else {
            i0 = (uint32_t)tbi_floor_clamp(pos, 0, (tbi_int)g->n - 1);
            if (i0 >= g->n - 1) i0 = g->n - 2;
            i1 = i0 + 1;
            w = pos - (tb_real)i0;
        }
        for (j = 0; j < S; j++) {
            tb_real v0 = (tb_real)g->ring[((oldest + i0) % g->cap) * S + j];
            tb_real v1 = (tb_real)g->ring[((oldest + i1) % g->cap) * S + j];
            tb_real v = v0 + w * (v1 - v0);
            x[j] = (v - PV(m, body + 1 + j)) / PV(m, body + 1 + S + j);
        }
        /* PyTorch GRU cell, gates (r, z, n), a gate at a time: its input and hidden sums for every
         * unit (gru_rows), then r into rr, z into hn, then hn = (1 - z) n + z h with
         * n = tanh(W_in x + b_in + r (W_hn h + b_hn)) */
        for (gate = 0; gate < 3; gate++) {
            gru_rows(m->payload + 4u * (m->off[O_A] + gate * H * S), m->payload + 4u * (m->off[O_C] + gate * H), x, S, H, si);
            gru_rows(m->payload + 4u * (m->off[O_B] + gate * H * H), m->payload + 4u * (m->off[O_D] + gate * H), h, H, H, sh);
            if (gate == 0)
                for (i = 0; i < H; i++) rr[i] = tbi_sigm(si[i] + sh[i]);
            else if (gate == 1)
                for (i = 0; i < H; i++) hn[i] = tbi_sigm(si[i] + sh[i]);
            else
                for (i = 0; i < H; i++) hn[i] = (1 - hn[i]) * tbm_tanh(si[i] + rr[i] * sh[i]) + hn[i] * h[i];
        }
        for (i = 0; i < H; i++) h[i] = hn[i];
    }
    p = (axis_mm - PV(m, body + 1 + 2 * S)) / PV(m, body + 2 + 2 * S);
    for (i = 0; i <= D; i++) {
        tb_real c = PV(m, m->off[O_F] + i);
        for (j = 0; j < H; j++) c += PV(m, m->off[O_E] + i * H + j) * h[j];
        out += c * pw;
        pw *= p;
    }
    *thermal = out * PV(m, body + 4 + 2 * S) + PV(m, body + 3 + 2 * S);
    return TB_OK;
}

const tbi_kind tbi_kind_gru = {
    .kind = TB_KIND_GRU, .max_version = 1, .pipeline = 1, .parse = parse, .carve = carve, .sample = sample,
    .predict = predict,
};
