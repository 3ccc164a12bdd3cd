/*
 * tb_kind_lumped.c - kind LUMPED: the lumped thermal network of a spindle (docs/concepts.md
 * "A lumped thermal network for a spindle", physics_spindle; written by
 * thermbench/export/lumped_encoding.py): a chain of first-order nodes heated by (u/u_ref)^p,
 * discretised exactly over a uniform grid (A_d, B_d precomputed at export), states
 * interpolated in time.
 */
#include "tb_internal.h"

/* lumped network (docs/concepts.md, "A lumped thermal network for a spindle"; written by
 * thermbench/export/lumped_encoding.py). dims [n, S, K, A]: n nodes, S sensors in the sensor
 * block, K unlagged sensor terms, A = 1 with a lagged ambient drive. Every real of the body is a
 * float32 (hi, lo) pair "R" (hi + lo: the double value): the recursion runs for days, and a
 * float32 A_d would move a node's rise by ~6e-8 / (1 - a) of itself (a = exp(-step / tau)).
 *   O_BODY  u_source (0 feed_mm_min, 1 axis_mm, 2 load_N, 3 input channel), u_channel,
 *           u_nonneg (1: u >= 0 required, a fractional power), step_s R, u_ref R, exponent R
 *   O_A     A_d, its lower triangle row by row: n (n + 1) / 2 R (diagonal exp(-step / tau_i))
 *   O_B     B_d: n R
 *   O_C     node gains c_i, um per unit rise: n R
 *   O_D     A = 1: ambient sensor index (in the sensor block), a = exp(-step / tau_a) R, gain c_a
 *           um/degC R
 *   O_E     K sensor indices, then their K gains, um/degC, R
 *   O_F     offset d, um, R */
enum { LU_SRC_FEED = 0, LU_SRC_AXIS, LU_SRC_LOAD, LU_SRC_CHANNEL };
#define LU_STEP(m) PR(m, (m)->off[O_BODY] + 3u)

/* grid states kept: every grid point one sample may close (a gap of up to TB_MAX_GAP_S), plus the
 * two a query interpolates between */
static uint32_t lump_grid_cap(const tb_model *m)
{
    return (uint32_t)tbi_floor_clamp(tbm_ceil(TB_MAX_GAP_S / LU_STEP(m) - TB_R(1e-9)), 0, 1 << 20) + 3u;
}

/* samples of the sensor terms kept: those since the oldest grid point kept (the samples lie on the
 * period's grid) and the one before it; 0 without sensor terms */
static tb_real lump_hist_samples(const tb_model *m)
{
    if (m->dims[2] == 0) return 0;
    return tbm_ceil((tb_real)lump_grid_cap(m) * LU_STEP(m) / PV(m, 0)) + 3;
}

typedef struct { /* lumped network (docs/concepts.md, physics_spindle) */
    uint32_t ns;           /* states per grid point: n nodes (+ 1: the lagged ambient rise) */
    uint32_t g_cap, r_cap; /* grid points kept; sensor-term samples kept */
    int started;
    tb_real t0;            /* the grid starts at the run's first process sample */
    tb_real acc_t;         /* the current interval [t0 + k step, ...) is integrated up to acc_t */
    tbi_count k;           /* intervals closed: the newest grid state is the one at t0 + k step */
    tb_real acc_q, acc_a;  /* integrals of the heat and of the ambient rise since t0 + k step */
    tb_real last_q, last_a; /* the last sample's heat and ambient rise, held to the next sample */
    tb_real *g;            /* g_cap x ns: grid state j in slot j % g_cap */
    tb_real *r_t;          /* r_cap ring: sample times */
    tb_real *r_v;          /* r_cap ring: sum_j s_j dT_j at the sample (the unlagged sensor terms) */
    uint32_t r_n, r_head;
} lump_t;

static void parse(tbi_cur *c, tb_model *m, uint16_t version)
{
    uint32_t *d = m->dims, i;
    uint32_t n = d[0], S = d[1], K = d[2], A = d[3], src, ch, j;
    (void)version;
    if (n < 1 || n > TB_MAX_LUMPED_NODES || S > TB_MAX_SENSORS || K > S || A > 1 || A > S) {
        c->err = TB_E_DIMS;
        return;
    }
    if (K > 0 && !(PV(m, 0) > 0)) { c->err = TB_E_PAYLOAD; return; } /* the terms' history needs the period */
    tbi_parse_sensors(c, m, S);
    tbi_parse_geom(c, m);
    m->off[O_BODY] = c->pos;
    src = tbi_take_int(c, 0, LU_SRC_CHANNEL);
    ch = tbi_take_int(c, 0, TB_MAX_SENSORS * 4u);
    tbi_take_int(c, 0, 1);                          /* u_nonneg */
    tbi_take_pair(c, TB_MIN_LUMPED_STEP_S, TB_R(1e6), 0); /* step_s */
    tbi_take_pair(c, 0, TB_R(1e30), 1);                   /* u_ref > 0 */
    tbi_take_pair(c, 0, 16, 1);                     /* exponent > 0 */
    m->off[O_A] = c->pos;
    for (i = 0; i < n && !c->err; i++) {
        tbi_take(c, 2 * i);           /* A_d[i][0..i-1] */
        tbi_take_pair(c, 0, 1, 0);    /* A_d[i][i] = exp(-step / tau_i) */
    }
    m->off[O_B] = tbi_take(c, 2 * n);
    m->off[O_C] = tbi_take(c, 2 * n);
    m->off[O_D] = c->pos;
    if (A) {
        tbi_take_int(c, 0, S - 1);
        tbi_take_pair(c, 0, 1, 0); /* exp(-step / tau_a) */
        tbi_take(c, 2);
    }
    m->off[O_E] = c->pos;
    for (j = 0; j < K && !c->err; j++) tbi_take_int(c, 0, S - 1);
    tbi_take(c, 2 * K);
    m->off[O_F] = tbi_take(c, 2);
    if (c->err) return;
    if (src != LU_SRC_CHANNEL && ch != 0) c->err = TB_E_PAYLOAD;
    if (src == LU_SRC_CHANNEL) {
        for (j = 0; j < S; j++) /* a temperature channel read as the operating input */
            if ((uint32_t)PV(m, m->off[O_SENS] + j) == ch) c->err = TB_E_PAYLOAD;
        if (ch + 1u > m->max_channel) m->max_channel = ch + 1u;
    }
    if (!c->err && lump_hist_samples(m) > (tb_real)TB_MAX_WINDOW) c->err = TB_E_DIMS;
}

static void carve(const tb_model *m, tbi_arena *a, void **ks)
{
    const uint32_t *d = m->dims;
    uint32_t ns = d[0] + d[3], gcap = lump_grid_cap(m), rcap = (uint32_t)lump_hist_samples(m);
    lump_t *L = (lump_t *)tbi_carve(a, sizeof(lump_t));
    tb_real *g = (tb_real *)tbi_carve(a, sizeof(tb_real) * gcap * ns);
    tb_real *rt = (tb_real *)tbi_carve(a, sizeof(tb_real) * (rcap ? rcap : 1u));
    tb_real *rv = (tb_real *)tbi_carve(a, sizeof(tb_real) * (rcap ? rcap : 1u));
    if (a->p && !a->err) {
        memset(L, 0, sizeof *L);
        L->ns = ns;
        L->g_cap = gcap;
        L->r_cap = rcap;
        L->g = g;
        L->r_t = rt;
        L->r_v = rv;
    }
    *ks = L;
}

/* docs/concepts.md, "A lumped thermal network for a spindle" (thermbench.models.lumped): the heat
 * q = (u/u_ref)^p of each sample is held to the next sample and averaged exactly over the intervals
 * of a grid of step_s from the run's first process sample; the chain advances one interval with the
 * exact discretisation theta' = A_d theta + B_d q (A_d lower triangular, from the file: no matrix
 * exponential here), the lagged ambient rise theta_a' = a theta_a + (1 - a) mean(dT_a); a query
 * interpolates the grid states linearly in time and adds the unlagged sensor terms at its time. */
typedef struct {
    uint32_t n, A, K, amb;
    tb_real h;
    tb_real u_ref, p, a_amb;
    tb_real ad[TB_MAX_LUMPED_NODES * (TB_MAX_LUMPED_NODES + 1u) / 2u], bd[TB_MAX_LUMPED_NODES];
} lump_par_t;

static void lump_params(const tb_model *m, lump_par_t *c)
{
    uint32_t b = m->off[O_BODY], i, tri;
    c->n = m->dims[0];
    c->K = m->dims[2];
    c->A = m->dims[3];
    c->h = LU_STEP(m);
    c->u_ref = PR(m, b + 5u);
    c->p = PR(m, b + 7u);
    tri = c->n * (c->n + 1u) / 2u;
    for (i = 0; i < tri; i++) c->ad[i] = PR(m, m->off[O_A] + 2u * i);
    for (i = 0; i < c->n; i++) c->bd[i] = PR(m, m->off[O_B] + 2u * i);
    c->amb = c->A ? (uint32_t)PV(m, m->off[O_D]) : 0;
    c->a_amb = c->A ? PR(m, m->off[O_D] + 1u) : 0;
}

/* the operating input of a sample (the core has made sure its channel is there) */
static tb_real op_input(const tb_model *m, const tb_sample *s)
{
    uint32_t b = m->off[O_BODY];
    switch ((uint32_t)PV(m, b)) {
    case LU_SRC_FEED: return s->feed_mm_min;
    case LU_SRC_AXIS: return s->axis_mm;
    case LU_SRC_LOAD: return s->load_N;
    default: return s->temps_C[(uint32_t)PV(m, b + 1u)];
    }
}

/* is the sample's operating input usable? (a negative value to a fractional power: thermbench
 * raises too) */
static int check(const tb_model *m, const void *ks, const tb_sample *s)
{
    uint32_t b = m->off[O_BODY];
    tb_real u = op_input(m, s);
    tb_real u_ref = PR(m, b + 5u);
    tb_real p = PR(m, b + 7u), q;
    (void)ks;
    if (!isfinite(u) || tbm_fabs(u) > TB_MAX_OPERATING) return TB_E_INPUT;
    if (u < 0 && (PV(m, b + 2u) != 0 || p != tbm_floor(p))) return TB_E_INPUT;
    q = tbm_pow(u / u_ref, p);
    if (!isfinite(q) || tbm_fabs(q) > TB_MAX_HEAT) return TB_E_INPUT;
    return TB_OK;
}

/* theta(k + 1) from theta(k) = x over one interval of mean heat q and mean ambient rise ra */
static void lump_advance(const lump_par_t *c, const tb_real *x, tb_real q, tb_real ra, tb_real *out)
{
    uint32_t i, j, row = 0;
    for (i = 0; i < c->n; i++) { /* the order of thermbench's lfilter sections */
        tb_real w = c->bd[i] * q;
        for (j = 0; j < i; j++) w += c->ad[row + j] * x[j];
        out[i] = w + c->ad[row + i] * x[i];
        row += i + 1u;
    }
    if (c->A) out[c->n] = (1 - c->a_amb) * ra + c->a_amb * x[c->n];
}

#define LU_SLOT(L, j) ((L)->g + (size_t)((j) % (L)->g_cap) * (L)->ns)

/* the held last sample integrated up to t, closing every interval that ends at or before t */
static void lump_integrate(const lump_par_t *c, lump_t *L, tb_real t)
{
    for (;;) {
        tb_real edge = L->t0 + (tb_real)(L->k + 1u) * c->h;
        if (t < edge) break;
        L->acc_q += L->last_q * (edge - L->acc_t);
        L->acc_a += L->last_a * (edge - L->acc_t);
        lump_advance(c, LU_SLOT(L, L->k), L->acc_q / c->h, L->acc_a / c->h, LU_SLOT(L, L->k + 1u));
        L->k++;
        L->acc_q = L->acc_a = 0;
        L->acc_t = edge;
    }
    L->acc_q += L->last_q * (t - L->acc_t);
    L->acc_a += L->last_a * (t - L->acc_t);
    L->acc_t = t;
}

static void sample(const tb_model *m, void *ks, const tbi_motion *mo, const tb_real *dT)
{
    lump_t *L = (lump_t *)ks;
    lump_par_t c;
    tb_real rv = 0;
    uint32_t j;
    lump_params(m, &c);
    for (j = 0; j < c.K; j++)
        rv += PR(m, m->off[O_E] + c.K + 2u * j) * dT[(uint32_t)PV(m, m->off[O_E] + j)];
    if (!L->started) { /* the run's first process sample: every node at rest (rise 0) */
        L->started = 1;
        L->t0 = L->acc_t = mo->t_s;
        for (j = 0; j < L->ns; j++) L->g[j] = 0;
    } else {
        lump_integrate(&c, L, mo->t_s);
    }
    L->last_q = tbm_pow(mo->op_u / c.u_ref, c.p);
    L->last_a = c.A ? dT[c.amb] : 0;
    if (L->r_cap) {
        L->r_t[L->r_head] = mo->t_s;
        L->r_v[L->r_head] = rv;
        L->r_head = (L->r_head + 1u) % L->r_cap;
        if (L->r_n < L->r_cap) L->r_n++;
    }
}

static void finish(const tb_model *m, void *ks)
{
    lump_t *L = (lump_t *)ks;
    /* thermbench simulates ceil(span / step) whole intervals (at least one), the last value held */
    lump_par_t c;
    tbi_count total;
    if (!L->started) return;
    lump_params(m, &c);
    total = tbi_steps_ceil((L->acc_t - L->t0) / c.h);
    if (L->k < total) lump_integrate(&c, L, L->t0 + (tb_real)total * c.h);
}

/* grid state k + ahead (ahead >= 1), before the samples that decide it: the current interval
 * completed with the last sample held, the later ones held throughout (exact once the log ended) */
static void lump_ahead(const lump_par_t *c, const lump_t *L, tbi_count ahead, tb_real *out)
{
    tb_real x[TB_MAX_LUMPED_NODES + 1u];
    tb_real edge = L->t0 + (tb_real)(L->k + 1u) * c->h;
    tbi_count i;
    uint32_t j;
    tb_real q = (L->acc_q + L->last_q * (edge - L->acc_t)) / c->h;
    tb_real ra = (L->acc_a + L->last_a * (edge - L->acc_t)) / c->h;
    lump_advance(c, LU_SLOT(L, L->k), q, ra, out);
    for (i = 1; i < ahead; i++) {
        for (j = 0; j < L->ns; j++) x[j] = out[j];
        lump_advance(c, x, L->last_q, L->last_a, out);
    }
}

/* the unlagged sensor terms at t, interpolated over the samples (numpy.interp over the log) */
static int lump_terms_at(const lump_t *L, tb_real t, tb_real *out)
{
    uint32_t oldest, lo, hi, cap = L->r_cap;
    if (L->r_n == 0) return TB_E_NOTREADY;
    oldest = (L->r_head + cap - L->r_n) % cap;
#define LU_R(i) ((oldest + (i)) % cap)
    if (t >= L->r_t[LU_R(L->r_n - 1u)]) {
        *out = L->r_v[LU_R(L->r_n - 1u)];
        return TB_OK;
    }
    if (t < L->r_t[oldest]) {
        if (L->r_n == cap) return TB_E_LATE;
        *out = L->r_v[oldest]; /* before the first sample: numpy clamps */
        return TB_OK;
    }
    lo = 0;
    hi = L->r_n - 1u; /* t[lo] <= t < t[hi] */
    while (hi - lo > 1u) {
        uint32_t mid = lo + (hi - lo) / 2u;
        if (L->r_t[LU_R(mid)] <= t) lo = mid;
        else hi = mid;
    }
    *out = tbi_interp1(t, L->r_t[LU_R(lo)], L->r_t[LU_R(hi)], L->r_v[LU_R(lo)], L->r_v[LU_R(hi)]);
#undef LU_R
    return TB_OK;
}

static int predict(const tb_model *m, const void *ks, tb_real t, tb_real axis_mm, tb_real *thermal)
{
    const lump_t *L = (const lump_t *)ks;
    lump_par_t c;
    tb_real xa[TB_MAX_LUMPED_NODES + 1u], xb[TB_MAX_LUMPED_NODES + 1u], out = 0, terms = 0;
    tb_real pos;
    tb_real w;
    tbi_count kq, oldest;
    uint32_t i, gains = m->off[O_C];
    (void)axis_mm; /* a spindle: the same error at every position (the geometric block aside) */
    if (!L->started) return TB_E_NOTREADY;
    lump_params(m, &c);
    pos = (t - L->t0) / c.h;
    if (pos < 0) pos = 0; /* before the log: at rest (thermbench clips the grid position) */
    if (pos >= (tb_real)L->k + (tb_real)L->g_cap) return TB_E_NOTREADY;
    kq = (tbi_count)tbm_floor(pos);
    w = pos - (tb_real)kq;
    oldest = L->k + 1u > L->g_cap ? L->k + 1u - L->g_cap : 0;
    if (kq < oldest) return TB_E_LATE;
    if (L->r_cap) {
        int rc = lump_terms_at(L, t, &terms);
        if (rc != TB_OK) return rc;
    }
    if (kq <= L->k) memcpy(xa, LU_SLOT(L, kq), sizeof(tb_real) * L->ns);
    else lump_ahead(&c, L, kq - L->k, xa);
    if (kq + 1u <= L->k) memcpy(xb, LU_SLOT(L, kq + 1u), sizeof(tb_real) * L->ns);
    else lump_ahead(&c, L, kq + 1u - L->k, xb);
    for (i = 0; i < c.n; i++) out += PR(m, gains + 2u * i) * ((1 - w) * xa[i] + w * xb[i]);
    if (c.A) out += PR(m, m->off[O_D] + 3u) * ((1 - w) * xa[c.n] + w * xb[c.n]);
    *thermal = out + PR(m, m->off[O_F]) + terms;
    return TB_OK;
}

/* the newest grid state: every value up to it is final */
static tb_real ready_s(const tb_model *m, const void *ks, tb_real *horizon_s)
{
    const lump_t *L = (const lump_t *)ks;
    if (horizon_s) *horizon_s = LU_STEP(m) + TB_MAX_GAP_S;
    return L->started ? L->t0 + (tb_real)L->k * LU_STEP(m) : TBI_NO_TIME;
}

const tbi_kind tbi_kind_lumped = {
    .kind = TB_KIND_LUMPED, .max_version = 1, .pipeline = 1, .parse = parse, .carve = carve, .check = check,
    .op_input = op_input, .sample = sample, .finish = finish, .ready_s = ready_s, .predict = predict,
};
