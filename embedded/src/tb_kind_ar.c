/*
 * tb_kind_ar.c - kind AR: seed 003 (our reading), an ARX model of the error curve's
 * coefficients on operating inputs (the feed, the load, to a power), advanced on a grid of
 * sample_s from the run's first sample with each interval's mean input; a query interpolates
 * the last two grid points in time.
 * dims [D, na, nb, nu]; body: origin, sample_s (>= 1 s); O_A nu x (column code 0 feed /
 * 1 load, power > 0); O_B ar[(D + 1) x na]; O_C input[(D + 1) x nb x nu]; O_D offset[D + 1].
 */
#include "tb_internal.h"

typedef struct {
    tb_real t0, edge_lo; /* current interval [edge_lo, edge_hi) */
    tbi_count k;         /* intervals closed */
    int started;
    tb_real *usum;     /* nu */
    uint32_t ucount;
    tb_real last_t;
    tb_real *last_v;   /* nu */
    tb_real *c_hist;   /* (na + 1) x (D + 1): c(k), c(k-1), ... newest first */
    tb_real *u_hist;   /* nb x nu: u(k), u(k-1), ... newest first */
    tb_real g_t[2];
    tb_real *g_c;      /* 2 x (D + 1): c at the last two grid points */
    int g_n, g_cur;
} ar_t;

static void parse(tbi_cur *c, tb_model *m, uint16_t version)
{
    uint32_t *d = m->dims, i;
    uint32_t D = d[0], na = d[1], nb = d[2], nu = d[3];
    (void)version;
    if (D > TB_MAX_POLY || na > TB_MAX_AR_ORDER || nb < 1 || nb > TB_MAX_AR_ORDER || nu < 1 || nu > 8) {
        c->err = TB_E_DIMS;
        return;
    }
    tbi_parse_sensors(c, m, 0);
    tbi_parse_geom(c, m);
    m->off[O_BODY] = tbi_take(c, 1); /* origin */
    tbi_take_val(c, 1, 1e7f, 0);     /* sample_s >= 1 s (seed 003: 600 s) */
    m->off[O_A] = c->pos;            /* terms: (column code 0 feed / 1 load, power > 0) */
    for (i = 0; i < nu && !c->err; i++) {
        tbi_take_int(c, 0, 1);
        tbi_take_val(c, 0, 16, 1);
    }
    m->off[O_B] = tbi_take(c, (D + 1) * na);
    m->off[O_C] = tbi_take(c, (D + 1) * nb * nu);
    m->off[O_D] = tbi_take(c, D + 1);
}

static void carve(const tb_model *m, tbi_arena *a, void **ks)
{
    const uint32_t *d = m->dims;
    uint32_t D1 = d[0] + 1, na = d[1], nb = d[2], nu = d[3];
    ar_t *r = (ar_t *)tbi_carve(a, sizeof(ar_t));
    tb_real *arr = (tb_real *)tbi_carve(a, sizeof(tb_real) * (2u * nu + (na + 1u) * D1 + nb * nu + 2u * D1));
    if (a->p && !a->err) {
        memset(r, 0, sizeof *r);
        memset(arr, 0, sizeof(tb_real) * (2u * nu + (na + 1u) * D1 + nb * nu + 2u * D1));
        r->usum = arr;
        r->last_v = arr + nu;
        r->c_hist = arr + 2 * nu;
        r->u_hist = r->c_hist + (na + 1) * D1;
        r->g_c = r->u_hist + nb * nu;
    }
    *ks = r;
}

/* a negative value to a fractional power (thermbench raises there too) */
static int check(const tb_model *m, const void *ks, const tb_sample *s)
{
    uint32_t j;
    (void)ks;
    for (j = 0; j < m->dims[3]; j++) {
        tb_real code = PV(m, m->off[O_A] + 2 * j), power = PV(m, m->off[O_A] + 2 * j + 1);
        tb_real v = code == 0 ? s->feed_mm_min : s->load_N;
        if (v < 0 && power != tbm_floor(power)) return TB_E_INPUT;
    }
    return TB_OK;
}

static tb_real ar_term(const tb_model *m, uint32_t i, const tbi_motion *mo)
{
    tb_real code = PV(m, m->off[O_A] + 2 * i), power = PV(m, m->off[O_A] + 2 * i + 1);
    tb_real v = code == 0 ? mo->feed_mm_min : mo->load_N;
    return power == 1 ? v : tbm_pow(v, power);
}

static void ar_close(const tb_model *m, ar_t *r, const tb_real *u)
{
    uint32_t D1 = m->dims[0] + 1, na = m->dims[1], nb = m->dims[2], nu = m->dims[3], i, a, b, q;
    tb_real cnew[TB_MAX_POLY + 1];
    /* shift in u(k) */
    for (b = nb; b-- > 1;)
        for (q = 0; q < nu; q++) r->u_hist[b * nu + q] = r->u_hist[(b - 1) * nu + q];
    for (q = 0; q < nu; q++) r->u_hist[q] = u[q];
    r->k++;
    for (i = 0; i < D1; i++) {
        tb_real acc = PV(m, m->off[O_D] + i);
        for (a = 0; a < na; a++) /* c(k-1-a): c_hist row a (newest first) */
            acc += PV(m, m->off[O_B] + i * na + a) * r->c_hist[a * D1 + i];
        for (b = 0; b < nb; b++)
            if (r->k >= (tbi_count)b + 1)
                for (q = 0; q < nu; q++) acc += PV(m, m->off[O_C] + (i * nb + b) * nu + q) * r->u_hist[b * nu + q];
        cnew[i] = acc;
    }
    for (a = na; a-- > 1;)
        for (i = 0; i < D1; i++) r->c_hist[a * D1 + i] = r->c_hist[(a - 1) * D1 + i];
    if (na > 0)
        for (i = 0; i < D1; i++) r->c_hist[i] = cnew[i];
    r->g_cur = 1 - r->g_cur;
    r->g_t[r->g_cur] = r->t0 + (tb_real)r->k * PV(m, m->off[O_BODY] + 1);
    for (i = 0; i < D1; i++) r->g_c[r->g_cur * D1 + i] = cnew[i];
    if (r->g_n < 2) r->g_n++;
}

static void ar_sample(const tb_model *m, ar_t *r, const tbi_motion *mo, int final)
{
    uint32_t nu = m->dims[3], q;
    tb_real dt = PV(m, m->off[O_BODY] + 1);
    tb_real v[8] = {0}, u[8] = {0};
    if (final) {
        /* thermbench simulates ceil(span / sample_s) intervals; the last one may be partial */
        tbi_count total;
        if (!r->started) return;
        total = tbi_steps_ceil((r->last_t - r->t0) / dt);
        while (r->k < total) {
            for (q = 0; q < nu; q++) u[q] = r->ucount ? r->usum[q] / (tb_real)r->ucount : r->last_v[q];
            ar_close(m, r, u);
            for (q = 0; q < nu; q++) r->usum[q] = 0;
            r->ucount = 0;
        }
        return;
    }
    if (!r->started) {
        r->started = 1;
        r->t0 = mo->t_s;
        r->g_t[0] = mo->t_s;
        r->g_n = 1;
        r->g_cur = 0;
    }
    for (q = 0; q < nu; q++) v[q] = ar_term(m, q, mo);
    for (;;) { /* close every interval [t0 + k dt, t0 + (k+1) dt) that this sample is past */
        tb_real hi = r->t0 + (tb_real)(r->k + 1) * dt;
        if (mo->t_s < hi) break;
        if (r->ucount > 0) {
            for (q = 0; q < nu; q++) u[q] = r->usum[q] / (tb_real)r->ucount;
        } else { /* no sample inside: the value interpolated at its middle */
            tb_real mid = r->t0 + ((tb_real)r->k + TB_R(0.5)) * dt;
            for (q = 0; q < nu; q++) u[q] = tbi_interp1(mid, r->last_t, mo->t_s, r->last_v[q], v[q]);
        }
        ar_close(m, r, u);
        for (q = 0; q < nu; q++) r->usum[q] = 0;
        r->ucount = 0;
    }
    for (q = 0; q < nu; q++) {
        r->usum[q] += v[q];
        r->last_v[q] = v[q];
    }
    r->ucount++;
    r->last_t = mo->t_s;
}

static int predict(const tb_model *m, const void *ks, tb_real t, tb_real axis_mm, tb_real *thermal)
{
    const ar_t *r = (const ar_t *)ks;
    uint32_t D1 = m->dims[0] + 1, i;
    int a, b;
    tb_real acc = 0, pw = 1, x = axis_mm - PV(m, m->off[O_BODY]);
    if (!r->started) return TB_E_NOTREADY;
    b = r->g_cur;
    a = r->g_n == 2 ? 1 - b : b;
    if (r->g_n == 2 && t < r->g_t[a]) return TB_E_LATE;
    for (i = 0; i < D1; i++) {
        tb_real c = tbi_interp1(t, r->g_t[a], r->g_t[b], r->g_c[a * D1 + i], r->g_c[b * D1 + i]);
        acc += c * pw;
        pw *= x;
    }
    *thermal = acc;
    return TB_OK;
}

static void sample(const tb_model *m, void *ks, const tbi_motion *mo, const tb_real *dT)
{
    (void)dT;
    ar_sample(m, (ar_t *)ks, mo, 0);
}

static void finish(const tb_model *m, void *ks) { ar_sample(m, (ar_t *)ks, 0, 1); }

static tb_real ready_s(const tb_model *m, const void *ks, tb_real *horizon_s)
{
    const ar_t *r = (const ar_t *)ks;
    if (horizon_s) *horizon_s = PV(m, m->off[O_BODY] + 1) + TB_MAX_GAP_S;
    return r->started ? r->g_t[r->g_cur] : TBI_NO_TIME;
}

const tbi_kind tbi_kind_ar = {
    .kind = TB_KIND_AR, .max_version = 1, .pipeline = 1, .parse = parse, .carve = carve, .check = check,
    .sample = sample, .finish = finish, .ready_s = ready_s, .predict = predict,
};
