/*
 * tb_runtime.c - thermbench embedded compensator runtime (see tb_runtime.h).
 *
 * C99, no heap, only <math.h> and <string.h>. Every read of a model file goes
 * through a bounds-checked cursor at open time; after a successful open the
 * layout is known to fit the payload, so evaluation indexes it directly.
 *
 * The equations and where they come from:
 *   filters      seed 002 §2.3.1 eq. 1-3 (limit filter, scalar Kalman)
 *   MLR curve    seed 002 eq. 6-11, seed 004 (curve coefficients linear in dT)
 *   MLR seed001  seed 001 eq. 12
 *   LSSVM        seed 002 eq. 12-14 (RBF kernel exp(-d^2 / (2 sigma^2)))
 *   physics      seed 000 §3.1-3.2 finite differences, §4.1 heat model,
 *                §4.3 compensation table (full-length error array, interpolated)
 *   AR           seed 003 (our reading: ARX of curve coefficients on feed)
 *   classifier   seed 002 §2.4 eq. 15-19 (proximity naive Bayes)
 *   lumped       docs/concepts.md "A lumped thermal network for a spindle" (physics_spindle):
 *                a chain of first-order nodes heated by (u/u_ref)^p, discretised exactly over
 *                a uniform grid (A_d, B_d precomputed at export), states interpolated in time
 */
#include "tb_runtime.h"

#include <math.h>
#include <string.h>

/* ------------------------------------------------------------------ utils */
static uint32_t rd_u32(const uint8_t *p)
{
    return (uint32_t)p[0] | ((uint32_t)p[1] << 8) | ((uint32_t)p[2] << 16) | ((uint32_t)p[3] << 24);
}

static uint16_t rd_u16(const uint8_t *p) { return (uint16_t)(p[0] | (p[1] << 8)); }

static float rd_f32(const uint8_t *p)
{
    uint32_t u = rd_u32(p);
    float f;
    memcpy(&f, &u, sizeof f);
    return f;
}

/* payload value i of a model (float32 -> tb_real) */
#define PV(m, i) ((tb_real)rd_f32((m)->payload + 4u * (uint32_t)(i)))

const char *tb_strerror(int code)
{
    switch (code) {
    case TB_OK: return "ok";
    case TB_E_SIZE: return "truncated file or length disagrees with the payload count";
    case TB_E_MAGIC: return "not a thermbench model file (bad magic)";
    case TB_E_VERSION: return "unsupported format version";
    case TB_E_KIND: return "unknown model kind";
    case TB_E_CRC: return "CRC-32 mismatch";
    case TB_E_DIMS: return "absurd or inconsistent dimensions";
    case TB_E_NAN: return "NaN or infinity in the payload";
    case TB_E_PAYLOAD: return "payload value out of its domain";
    case TB_E_ARENA: return "arena too small or misaligned";
    case TB_E_STATE: return "call out of order or wrong model kind";
    case TB_E_INPUT: return "bad sample";
    case TB_E_SAMPLING: return "log not sampled at the model's period";
    case TB_E_LATE: return "query older than the state held";
    case TB_E_NOTREADY: return "no state yet";
    case TB_E_ARG: return "bad argument";
    default: return "unknown error";
    }
}

int tb_crc32_check(const uint8_t *file, size_t len, uint32_t *crc_out)
{
    uint32_t crc = 0xFFFFFFFFu;
    size_t i;
    int k;
    if (!file && len) return TB_E_ARG;
    for (i = 0; i < len; i++) {
        crc ^= file[i];
        for (k = 0; k < 8; k++) crc = (crc >> 1) ^ (0xEDB88320u & (0u - (crc & 1u)));
    }
    if (crc_out) *crc_out = crc ^ 0xFFFFFFFFu;
    return TB_OK;
}

/* floor(v) as an integer clamped to [lo, hi] (NaN -> lo): no float-to-int overflow */
static int64_t floor_clamp(double v, int64_t lo, int64_t hi)
{
    if (!(v >= (double)lo)) return lo;
    if (v >= (double)hi) return hi;
    return (int64_t)floor(v);
}

static double interp1(double t, double t0, double t1, double v0, double v1)
{
    /* numpy.interp between two samples, clamped */
    if (t <= t0 || t1 <= t0) return v0;
    if (t >= t1) return v1;
    return v0 + (t - t0) * ((v1 - v0) / (t1 - t0));
}

/* --------------------------------------------------------- parse cursor */
typedef struct {
    const tb_model *m;
    uint32_t pos;
    int err;
} cur_t;

static uint32_t take(cur_t *c, uint32_t n)
{
    uint32_t at = c->pos;
    if (c->err) return 0;
    if (n > c->m->n_payload || c->pos > c->m->n_payload - n) {
        c->err = TB_E_DIMS;
        return 0;
    }
    c->pos += n;
    return at;
}

/* an integer-valued payload entry in [lo, hi] */
static uint32_t take_int(cur_t *c, uint32_t lo, uint32_t hi)
{
    uint32_t at = take(c, 1);
    tb_real v;
    if (c->err) return 0;
    v = PV(c->m, at);
    if (!(v >= (tb_real)lo && v <= (tb_real)hi) || v != floor(v)) {
        c->err = TB_E_PAYLOAD;
        return 0;
    }
    return (uint32_t)v;
}

/* a float32 (hi, lo) pair: a double-precision value (hi + lo) in [lo, hi] ((lo, hi] if strict_lo) */
static tb_real take_pair(cur_t *c, double lo, double hi, int strict_lo)
{
    uint32_t at = take(c, 2);
    double v;
    if (c->err) return 0;
    v = (double)rd_f32(c->m->payload + 4u * at) + (double)rd_f32(c->m->payload + 4u * (at + 1u));
    if ((strict_lo ? !(v > lo) : !(v >= lo)) || !(v <= hi)) {
        c->err = TB_E_PAYLOAD;
        return 0;
    }
    return (tb_real)v;
}

static tb_real take_val(cur_t *c, tb_real lo, tb_real hi, int strict_lo)
{
    uint32_t at = take(c, 1);
    tb_real v;
    if (c->err) return 0;
    v = PV(c->m, at);
    if ((strict_lo ? !(v > lo) : !(v >= lo)) || !(v <= hi)) {
        c->err = TB_E_PAYLOAD;
        return 0;
    }
    return v;
}

/* ------------------------------------------------ section offsets (off[]) */
enum {
    O_PERIOD = 0, /* sample period, s (0: any) */
    O_SENS,       /* sensor block */
    O_GEOM,       /* geometric block */
    O_BODY,       /* kind-specific body */
    O_A, O_B, O_C, O_D, O_E, O_F, /* kind-specific sub-sections */
    O_COUNT
};

typedef char off_fits_[(sizeof(((tb_model *)0)->off) / sizeof(uint32_t) >= O_COUNT) ? 1 : -1];

#define FSTEP_VALS 5u /* type, p1 (hi, lo), p2 (hi, lo): float32 pairs keep the double thresholds */
#define SENS_PER (1u + FSTEP_VALS * TB_MAX_FILTER_STEPS)

/* sensor block: S channel indices, then per sensor [n_steps, (type, p1, p2) x 4] */
static void parse_sensors(cur_t *c, tb_model *m, uint32_t S)
{
    uint32_t j, k, at;
    m->off[O_SENS] = c->pos;
    m->n_sensors = S;
    m->max_channel = 0;
    for (j = 0; j < S; j++) {
        uint32_t ch = take_int(c, 0, TB_MAX_SENSORS * 4u);
        if (ch + 1u > m->max_channel) m->max_channel = ch + 1u;
    }
    for (j = 0; j < S && !c->err; j++) {
        uint32_t n = take_int(c, 0, TB_MAX_FILTER_STEPS);
        at = take(c, FSTEP_VALS * TB_MAX_FILTER_STEPS);
        if (c->err) return;
        for (k = 0; k < TB_MAX_FILTER_STEPS; k++) {
            tb_real type = PV(m, at + FSTEP_VALS * k);
            tb_real p1 = PV(m, at + FSTEP_VALS * k + 1) + PV(m, at + FSTEP_VALS * k + 2);
            tb_real p2 = PV(m, at + FSTEP_VALS * k + 3) + PV(m, at + FSTEP_VALS * k + 4);
            if (k >= n) {
                if (type != 0) c->err = TB_E_PAYLOAD;
                continue;
            }
            if (type == 1) { /* limit: limit_C > 0, max_hold >= 0 integer (0: none) */
                if (!(p1 > 0) || !(p2 >= 0) || p2 != floor(p2) || p2 > 1e9) c->err = TB_E_PAYLOAD;
            } else if (type == 2) { /* Kalman: R > 0, Q > 0 */
                if (!(p1 > 0) || !(p2 > 0)) c->err = TB_E_PAYLOAD;
            } else {
                c->err = TB_E_PAYLOAD;
            }
        }
    }
}

/* geometric block: [gtype, n, off, scl, data..., m, origin, extra coefs...]
 * gtype 0 none, 1 polynomial sum c_i (off + scl x)^i (numpy Polynomial with its domain
 * map), 2 table (x strictly increasing, then y; linear in between, clamped) */
static void parse_geom(cur_t *c, tb_model *m)
{
    uint32_t gtype, n, at, i, extra;
    m->off[O_GEOM] = c->pos;
    gtype = take_int(c, 0, 2);
    n = take_int(c, 0, TB_MAX_TABLE);
    take(c, 2);
    if (c->err) return;
    if (gtype == 0 && n != 0) c->err = TB_E_PAYLOAD;
    if (gtype == 1 && (n < 1 || n > TB_MAX_POLY)) c->err = TB_E_DIMS;
    if (gtype == 2 && n < 1) c->err = TB_E_DIMS;
    if (c->err) return;
    at = take(c, gtype == 2 ? 2u * n : n);
    if (c->err) return;
    if (gtype == 2)
        for (i = 1; i < n; i++)
            if (!(PV(m, at + i) > PV(m, at + i - 1))) c->err = TB_E_PAYLOAD;
    extra = take_int(c, 0, TB_MAX_POLY);
    take(c, 1 + extra);
}

static tb_real poly_eval(const tb_model *m, uint32_t at, uint32_t n, tb_real u)
{
    tb_real acc = 0;
    while (n > 0) {
        n--;
        acc = acc * u + PV(m, at + n);
    }
    return acc;
}

double tb_model_geometric_um(const tb_model *m, double axis_mm)
{
    uint32_t g, gtype, n, extra, base;
    tb_real out = 0, x = (tb_real)axis_mm;
    if (!m || !m->payload || m->kind == TB_KIND_CLASSIFIER) return 0.0;
    g = m->off[O_GEOM];
    gtype = (uint32_t)PV(m, g);
    n = (uint32_t)PV(m, g + 1);
    base = g + 4;
    if (gtype == 1) {
        out = poly_eval(m, base, n, PV(m, g + 2) + PV(m, g + 3) * x);
    } else if (gtype == 2) {
        uint32_t lo = 0, hi = n - 1;
        if (x <= PV(m, base)) out = PV(m, base + n);
        else if (x >= PV(m, base + n - 1)) out = PV(m, base + 2 * n - 1);
        else {
            while (hi - lo > 1) { /* x[lo] < x < x[hi] */
                uint32_t mid = (lo + hi) / 2;
                if (PV(m, base + mid) <= x) lo = mid; else hi = mid;
            }
            out = (tb_real)interp1(x, PV(m, base + lo), PV(m, base + hi), PV(m, base + n + lo),
                                   PV(m, base + n + hi));
        }
    }
    base += gtype == 2 ? 2 * n : (gtype == 1 ? n : 0);
    extra = (uint32_t)PV(m, base);
    if (extra) out += poly_eval(m, base + 2, extra, x - PV(m, base + 1));
    return (double)out;
}

/* ---------------------------------------------------------------- arena */
typedef struct {
    uint8_t *p;
    size_t used, cap;
    int err;
} arena_t;

static void *carve(arena_t *a, size_t bytes)
{
    size_t at = (a->used + 7u) & ~(size_t)7u;
    if (a->err || bytes > a->cap || at > a->cap - bytes) {
        a->err = 1;
        return 0;
    }
    a->used = at + bytes;
    return a->p ? a->p + at : 0;
}

/* ----------------------------------------------- common sensor pipeline */
/* Every model except the classifier passes samples through this stage: the first
 * TB_START_SAMPLES + 1 samples are buffered (the limit filter decides its start value
 * from the next 5 readings, seed 002 §2.3.1 as implemented in thermbench), then every
 * sample is filtered per channel and its rise dT above the first filtered value kept
 * in a short history for interpolation. */
#define NBUF (TB_START_SAMPLES + 1u)
#define NHIST (NBUF + 1u) /* the startup buffer is processed at once; queries in it still interpolate */

typedef struct {
    tb_real prev, last_rej, est, P;
    uint32_t run;
    int started;
} fstate_t;

typedef struct {
    double t_s, axis_mm, feed_mm_min, load_N;
    double op_u; /* the operating input of a lumped network (0 for the other kinds) */
    int measuring;
} motion_t;

typedef struct {
    uint32_t S, n_steps; /* channels; filter steps allocated per channel */
    uint32_t n_in;      /* samples received */
    uint32_t started;   /* startup buffer flushed */
    double period_s;
    double t_first, t_last; /* first and last accepted sample */
    motion_t buf[NBUF];
    tb_real *buf_T;     /* NBUF x S raw temperatures */
    fstate_t *fs;       /* S x TB_MAX_FILTER_STEPS */
    tb_real *T0;        /* first filtered value per channel */
    /* history of processed samples */
    uint32_t h_n, h_head;
    double h_t[NHIST];
    tb_real *h_dT;      /* NHIST x S */
} common_t;

static uint32_t max_steps(const tb_model *m)
{
    uint32_t j, mx = 0;
    for (j = 0; j < m->n_sensors; j++) {
        uint32_t n = (uint32_t)PV(m, m->off[O_SENS] + m->n_sensors + SENS_PER * j);
        if (n > mx) mx = n;
    }
    return mx ? mx : 1;
}

static void common_carve(const tb_model *m, arena_t *a, common_t **cm, uint32_t S)
{
    uint32_t ns = max_steps(m);
    common_t *c = (common_t *)carve(a, sizeof(common_t));
    tb_real *bt = (tb_real *)carve(a, sizeof(tb_real) * NBUF * (S ? S : 1));
    fstate_t *fs = (fstate_t *)carve(a, sizeof(fstate_t) * ns * (S ? S : 1));
    tb_real *t0 = (tb_real *)carve(a, sizeof(tb_real) * (S ? S : 1));
    tb_real *hd = (tb_real *)carve(a, sizeof(tb_real) * NHIST * (S ? S : 1));
    if (a->p && !a->err) {
        memset(c, 0, sizeof *c);
        c->S = S;
        c->buf_T = bt;
        c->fs = fs;
        c->T0 = t0;
        c->h_dT = hd;
        c->n_steps = ns;
        memset(fs, 0, sizeof(fstate_t) * ns * (S ? S : 1));
    }
    *cm = c;
}

/* one filter step on one value (streaming; the limit filter's start handled by the caller) */
static tb_real fstep_apply(const tb_model *m, uint32_t at, fstate_t *f, tb_real z)
{
    tb_real type = PV(m, at), p1 = PV(m, at + 1) + PV(m, at + 2), p2 = PV(m, at + 3) + PV(m, at + 4);
    if (type == 1) { /* seed 002 eq. 1 with thermbench's last-accepted rule and max_hold */
        uint32_t max_hold = (uint32_t)p2;
        if (!f->started) {
            f->started = 1;
            f->prev = z;
            return z;
        }
        if (fabs((double)(z - f->prev)) <= (double)p1) {
            f->prev = z;
            f->run = 0;
            return z;
        }
        if (max_hold > 0) {
            f->run = (f->run && fabs((double)(z - f->last_rej)) <= (double)p1) ? f->run + 1 : 1;
            f->last_rej = z;
            if (f->run > max_hold) {
                f->prev = z;
                f->run = 0;
                return z;
            }
        }
        return f->prev;
    }
    /* Kalman, seed 002 eq. 2-3: x0 = z0, P0 = R */
    if (!f->started) {
        f->started = 1;
        f->est = z;
        f->P = p1;
        return z;
    }
    {
        tb_real Pp = f->P + p2;
        tb_real K = Pp / (Pp + p1);
        f->est = f->est + K * (z - f->est);
        f->P = (1 - K) * Pp;
        return f->est;
    }
}

static int cmp_real(tb_real a, tb_real b) { return a < b ? -1 : (a > b ? 1 : 0); }

/* median of n <= 5 values (numpy: mean of the two middle ones for even n) */
static tb_real median_small(const tb_real *v, uint32_t n)
{
    tb_real s[NBUF];
    uint32_t i, j;
    for (i = 0; i < n; i++) {
        tb_real x = v[i];
        for (j = i; j > 0 && cmp_real(s[j - 1], x) > 0; j--) s[j] = s[j - 1];
        s[j] = x;
    }
    return (n % 2) ? s[n / 2] : (s[n / 2 - 1] + s[n / 2]) / 2;
}

/* run the buffered startup samples of channel j through its chain, in place */
static void chain_batch(const tb_model *m, common_t *c, uint32_t j, tb_real *v, uint32_t n)
{
    uint32_t s_at = m->off[O_SENS] + c->S + SENS_PER * j;
    uint32_t k, i, nsteps = (uint32_t)PV(m, s_at);
    for (k = 0; k < nsteps; k++) {
        uint32_t at = s_at + 1 + FSTEP_VALS * k;
        fstate_t *f = &c->fs[j * c->n_steps + k];
        if (PV(m, at) == 1 && n >= 2) { /* limit filter: first reading a glitch the next ones agree on? */
            uint32_t nn = n - 1 < TB_START_SAMPLES ? n - 1 : TB_START_SAMPLES;
            tb_real med = median_small(v + 1, nn), lo = v[1], hi = v[1];
            for (i = 2; i <= nn; i++) {
                if (v[i] < lo) lo = v[i];
                if (v[i] > hi) hi = v[i];
            }
            double limit = (double)(PV(m, at + 1) + PV(m, at + 2));
            if (fabs((double)(v[0] - med)) > limit && (double)(hi - lo) <= limit)
                v[0] = med;
        }
        for (i = 0; i < n; i++) v[i] = fstep_apply(m, at, f, v[i]);
    }
}

static tb_real chain_one(const tb_model *m, common_t *c, uint32_t j, tb_real z)
{
    uint32_t s_at = m->off[O_SENS] + c->S + SENS_PER * j;
    uint32_t k, nsteps = (uint32_t)PV(m, s_at);
    for (k = 0; k < nsteps; k++)
        z = fstep_apply(m, s_at + 1 + FSTEP_VALS * k, &c->fs[j * c->n_steps + k], z);
    return z;
}

/* dT of channel j at history slot h */
#define HDT(c, h, j) ((c)->h_dT[(h) * (c)->S + (j)])

static void hist_push(common_t *c, double t, const tb_real *dT)
{
    uint32_t j, h = c->h_head;
    c->h_t[h] = t;
    for (j = 0; j < c->S; j++) HDT(c, h, j) = dT[j];
    c->h_head = (h + 1) % NHIST;
    if (c->h_n < NHIST) c->h_n++;
}

/* dT of every channel at t, interpolated in the history (numpy.interp over the log) */
static int hist_at(const common_t *c, double t, tb_real *out)
{
    uint32_t j, i, newest, oldest, a, b;
    if (c->h_n == 0) return TB_E_NOTREADY;
    newest = (c->h_head + NHIST - 1) % NHIST;
    oldest = (c->h_head + NHIST - c->h_n) % NHIST;
    if (t >= c->h_t[newest]) {
        for (j = 0; j < c->S; j++) out[j] = HDT(c, newest, j);
        return TB_OK;
    }
    if (t < c->h_t[oldest]) {
        if (c->h_n < NHIST) { /* before the first sample: numpy clamps */
            for (j = 0; j < c->S; j++) out[j] = HDT(c, oldest, j);
            return TB_OK;
        }
        return TB_E_LATE;
    }
    b = newest;
    for (i = 1; i < c->h_n; i++) {
        a = (b + NHIST - 1) % NHIST;
        if (c->h_t[a] <= t) {
            for (j = 0; j < c->S; j++)
                out[j] = (tb_real)interp1(t, c->h_t[a], c->h_t[b], HDT(c, a, j), HDT(c, b, j));
            return TB_OK;
        }
        b = a;
    }
    for (j = 0; j < c->S; j++) out[j] = HDT(c, oldest, j);
    return TB_OK;
}

/* ------------------------------------------------------ kind interface */
typedef struct {
    common_t *cm;
    void *ks;     /* kind state */
    int finished; /* tb_model_finish was called: no more samples */
} state_t;

static void kind_carve(const tb_model *m, arena_t *a, void **ks);
static void kind_sample(tb_model *m, state_t *st, const motion_t *mo, const tb_real *dT);
static void kind_finish(tb_model *m, state_t *st);

static void process_sample(tb_model *m, state_t *st, const motion_t *mo, tb_real *filtered)
{
    common_t *c = st->cm;
    tb_real dT[TB_MAX_SENSORS];
    uint32_t j;
    if (c->h_n == 0 && c->n_in >= 1) {
        for (j = 0; j < c->S; j++) c->T0[j] = filtered[j];
    }
    for (j = 0; j < c->S; j++) dT[j] = filtered[j] - c->T0[j];
    hist_push(c, mo->t_s, dT);
    kind_sample(m, st, mo, dT);
}

static void flush_start(tb_model *m, state_t *st)
{
    common_t *c = st->cm;
    uint32_t n = c->n_in < NBUF ? c->n_in : NBUF, i, j;
    tb_real col[NBUF], filt[TB_MAX_SENSORS];
    tb_real *out = c->buf_T; /* filtered in place, column by column */
    for (j = 0; j < c->S; j++) {
        for (i = 0; i < n; i++) col[i] = c->buf_T[i * c->S + j];
        chain_batch(m, c, j, col, n);
        for (i = 0; i < n; i++) out[i * c->S + j] = col[i];
    }
    c->started = 1;
    for (i = 0; i < n; i++) {
        for (j = 0; j < c->S; j++) filt[j] = out[i * c->S + j];
        process_sample(m, st, &c->buf[i], filt);
    }
}

/* ------------------------------------------------------------- open */
static void parse_kind(cur_t *c, tb_model *m);
static double horizon_s(const tb_model *m);

int tb_model_open(tb_model *m, const uint8_t *file, size_t len)
{
    uint32_t n_payload, crc, i;
    uint16_t version, kind, n_dims;
    cur_t c;
    if (!m) return TB_E_ARG;
    memset(m, 0, sizeof *m);
    if (!file) return TB_E_ARG;
    if (len < TB_HEADER_BYTES + 4u) return TB_E_SIZE;
    if (memcmp(file, TB_MAGIC, 4) != 0) return TB_E_MAGIC;
    version = rd_u16(file + 4);
    if (version != TB_FORMAT_VERSION) return TB_E_VERSION;
    kind = rd_u16(file + 6);
    n_dims = rd_u16(file + 8);
    n_payload = rd_u32(file + 44);
    if (n_payload > TB_MAX_PAYLOAD) return TB_E_DIMS;
    if ((size_t)n_payload * 4u + TB_HEADER_BYTES + 4u != len) return TB_E_SIZE;
    tb_crc32_check(file, len - 4u, &crc);
    if (crc != rd_u32(file + len - 4u)) return TB_E_CRC;
    if (kind < 1 || kind > TB_KIND_MAX) return TB_E_KIND;
    if (n_dims > TB_MAX_DIMS || rd_u16(file + 10) != 0) return TB_E_DIMS;
    for (i = 0; i < TB_MAX_DIMS; i++) {
        m->dims[i] = rd_u32(file + 12 + 4 * i);
        if (i >= n_dims && m->dims[i] != 0) return TB_E_DIMS;
    }
    m->payload = file + TB_HEADER_BYTES;
    m->n_payload = n_payload;
    m->kind = kind;
    for (i = 0; i < n_payload; i++) {
        float f = rd_f32(m->payload + 4u * i);
        if (!isfinite(f)) {
            memset(m, 0, sizeof *m);
            return TB_E_NAN;
        }
    }
    c.m = m;
    c.pos = 0;
    c.err = 0;
    m->off[O_PERIOD] = take(&c, 1);
    if (!c.err && !(PV(m, 0) >= 0 && PV(m, 0) <= 3600)) c.err = TB_E_PAYLOAD;
    parse_kind(&c, m);
    if (!c.err && c.pos != n_payload) c.err = TB_E_DIMS;
    if (c.err) {
        int e = c.err;
        memset(m, 0, sizeof *m);
        return e;
    }
    return TB_OK;
}

/* ------------------------------------------------------------ kinds */
/* dims: MLR_CURVE [S, D]; MLR_SEED001 [S=2, m]; LSSVM [S, N]; MLP [S, L, act];
 * GRU [S, H, D, K]; PHYSICS [S (0/1), n_nodes]; AR [D, na, nb, nu];
 * CLASSIFIER [K, nA, nB, nC]; LUMPED [n, S, K, A] */
enum { ACT_TANH = 1, ACT_RELU, ACT_GELU, ACT_SILU, ACT_SIGMOID };
enum { PHY_NPARAM = 41 };
enum {
    P_DX, P_DT, P_PER_STEP, P_MACRO, P_NODES, P_NB, P_NUT_LEN, P_BEAR_LEN, P_L, P_CAP, P_COND, P_SIDE, P_END,
    P_ALPHA, P_K1, P_K2, P_K3, P_K4, P_PF, P_AMB_MODE, P_AMB_AMP, P_AMB_PERIOD, P_AMB_PHASE, P_AMB_RATE,
    P_FREE, P_KF, P_FREE_K, P_MOTOR, P_KMOTOR, P_TAU_MOTOR, P_K5, P_LOAD, P_K6, P_FF, P_KAPPA, P_OD, P_BETA,
    P_H_TAU, P_H_GAIN_W, P_H_GAIN_V, P_H_COUPLING
};

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
#define PR(m, i) (PV(m, i) + PV(m, (i) + 1u))
#define LU_STEP(m) ((double)PV(m, (m)->off[O_BODY] + 3u) + (double)PV(m, (m)->off[O_BODY] + 4u))

/* grid states kept: every grid point one sample may close (a gap of up to TB_MAX_GAP_S), plus the
 * two a query interpolates between */
static uint32_t lump_grid_cap(const tb_model *m)
{
    return (uint32_t)floor_clamp(ceil(TB_MAX_GAP_S / LU_STEP(m) - 1e-9), 0, 1 << 20) + 3u;
}

/* samples of the sensor terms kept: those since the oldest grid point kept (the samples lie on the
 * period's grid) and the one before it; 0 without sensor terms */
static double lump_hist_samples(const tb_model *m)
{
    if (m->dims[2] == 0) return 0;
    return ceil((double)lump_grid_cap(m) * LU_STEP(m) / (double)PV(m, 0)) + 3.0;
}

static void parse_kind(cur_t *c, tb_model *m)
{
    uint32_t *d = m->dims, i, at;
    switch (m->kind) {
    case TB_KIND_MLR_CURVE:
        if (d[0] > TB_MAX_SENSORS || d[1] > TB_MAX_POLY) { c->err = TB_E_DIMS; return; }
        parse_sensors(c, m, d[0]);
        parse_geom(c, m);
        m->off[O_BODY] = take(c, 1 + (d[1] + 1) * (d[0] + 1));
        break;
    case TB_KIND_MLR_SEED001:
        if (d[0] != 2 || d[1] < 1 || d[1] > 8) { c->err = TB_E_DIMS; return; }
        parse_sensors(c, m, 2);
        parse_geom(c, m);
        m->off[O_BODY] = take(c, 1 + d[1] + 2);
        break;
    case TB_KIND_LSSVM:
        if (d[0] > TB_MAX_SENSORS || d[1] < 1 || d[1] > TB_MAX_SUPPORT) { c->err = TB_E_DIMS; return; }
        parse_sensors(c, m, d[0]);
        parse_geom(c, m);
        m->off[O_BODY] = take(c, 2 * (d[0] + 1));
        for (i = 0; i <= d[0] && !c->err; i++)
            if (!(PV(m, m->off[O_BODY] + d[0] + 1 + i) > 0)) c->err = TB_E_PAYLOAD;
        take_val(c, 0, 1e30f, 1); /* sigma2 > 0 */
        take(c, 2);               /* b as float32 hi + lo */
        m->off[O_A] = take(c, 2 * d[1]); /* alpha hi[N], lo[N]: float32 alone loses ~1e-8 |alpha| */
        m->off[O_B] = take(c, d[1] * (d[0] + 1));
        break;
    case TB_KIND_MLP: {
        uint32_t width = d[0] + 1, L = d[1];
        if (d[0] > TB_MAX_SENSORS || L < 1 || L > TB_MAX_LAYERS || d[2] < ACT_TANH || d[2] > ACT_SIGMOID) {
            c->err = TB_E_DIMS;
            return;
        }
        parse_sensors(c, m, d[0]);
        parse_geom(c, m);
        m->off[O_BODY] = take(c, 2 * (d[0] + 1));
        for (i = 0; i <= d[0] && !c->err; i++)
            if (!(PV(m, m->off[O_BODY] + d[0] + 1 + i) > 0)) c->err = TB_E_PAYLOAD;
        take(c, 1);
        take_val(c, 0, 1e30f, 1); /* y scale > 0 */
        m->off[O_A] = c->pos; /* widths */
        for (i = 0; i < L && !c->err; i++) {
            uint32_t w = take_int(c, 1, TB_MAX_WIDTH);
            if (i == L - 1 && w != 1) c->err = TB_E_DIMS;
        }
        m->off[O_B] = c->pos; /* layers */
        for (i = 0; i < L && !c->err; i++) {
            uint32_t w = (uint32_t)PV(m, m->off[O_A] + i);
            take(c, w * width + w);
            width = w;
        }
        break;
    }
    case TB_KIND_GRU: {
        uint32_t S = d[0], H = d[1], D = d[2], K = d[3];
        if (S < 1 || S > TB_MAX_SENSORS || H < 1 || H > TB_MAX_GRU_HIDDEN || D > TB_MAX_POLY || K > TB_MAX_LAGS) {
            c->err = TB_E_DIMS;
            return;
        }
        if (!(PV(m, 0) > 0)) { c->err = TB_E_PAYLOAD; return; } /* needs the sample period */
        parse_sensors(c, m, S);
        parse_geom(c, m);
        m->off[O_BODY] = c->pos;
        take_val(c, 1e-3f, 1e7f, 0); /* step_s */
        at = take(c, 2 * S);
        for (i = 0; i < S && !c->err; i++)
            if (!(PV(m, at + S + i) > 0)) c->err = TB_E_PAYLOAD;
        take(c, 1);
        take_val(c, 0, 1e30f, 1); /* p scale */
        take(c, 1);
        take_val(c, 0, 1e30f, 1); /* y scale */
        m->off[O_A] = take(c, 3 * H * S);
        m->off[O_B] = take(c, 3 * H * H);
        m->off[O_C] = take(c, 3 * H);
        m->off[O_D] = take(c, 3 * H);
        m->off[O_E] = take(c, (D + 1) * H);
        m->off[O_F] = take(c, D + 1);
        if (!c->err && (double)K * (double)PV(m, m->off[O_BODY]) / (double)PV(m, 0) > (double)TB_MAX_WINDOW)
            c->err = TB_E_DIMS;
        if (!c->err && (double)(K + 1) * 3.0 * (double)H * (double)(H + S) > 2e7) c->err = TB_E_DIMS; /* work per predict */
        break;
    }
    case TB_KIND_PHYSICS: {
        uint32_t n;
        tb_real dx, dt;
        if (d[0] > 1 || d[1] < 2 || d[1] > TB_MAX_NODES) { c->err = TB_E_DIMS; return; }
        parse_sensors(c, m, d[0]);
        parse_geom(c, m);
        m->off[O_BODY] = at = take(c, PHY_NPARAM);
        if (c->err) return;
        n = d[1];
        dx = PV(m, at + P_DX);
        dt = PV(m, at + P_DT);
        if (!(dx > 0) || !(dt > 0) || PV(m, at + P_NODES) != (tb_real)n || !(PV(m, at + P_PER_STEP) >= 1) ||
            PV(m, at + P_PER_STEP) != floor(PV(m, at + P_PER_STEP)) || PV(m, at + P_PER_STEP) > 1e6 ||
            !(PV(m, at + P_MACRO) / PV(m, at + P_PER_STEP) >= (tb_real)1e-3) || PV(m, at + P_MACRO) > 1e5 ||
            PV(m, at + P_MACRO) < (tb_real)0.1 || (double)n * (double)PV(m, at + P_PER_STEP) > 4e6 ||
            !(fabs((double)(PV(m, at + P_L) / dx) - (double)n) <= 0.5 + 1e-6 * (double)n ||
              (n == 2 && (double)(PV(m, at + P_L) / dx) < 2.5)) ||
            !(PV(m, at + P_NB) >= 0) || PV(m, at + P_NB) > (tb_real)n ||
            PV(m, at + P_NB) != floor(PV(m, at + P_NB)) || !(PV(m, at + P_NUT_LEN) > 0) ||
            !(PV(m, at + P_L) > 0) || !(PV(m, at + P_CAP) > 0) || !(PV(m, at + P_COND) >= 0) ||
            (PV(m, at + P_NB) > 0 && !(PV(m, at + P_BEAR_LEN) > 0)) || PV(m, at + P_AMB_MODE) < 0 ||
            PV(m, at + P_AMB_MODE) != floor(PV(m, at + P_AMB_MODE)) ||
            PV(m, at + P_AMB_MODE) > 2 || (PV(m, at + P_AMB_MODE) == 1) != (d[0] == 1) ||
            (PV(m, at + P_AMB_MODE) == 2 && !(PV(m, at + P_AMB_PERIOD) > 0)) ||
            !(PV(m, at + P_FREE_K) >= (PV(m, at + P_FREE) != 0 ? 1 : 0)) || PV(m, at + P_FREE_K) > (tb_real)n ||
            PV(m, at + P_FREE_K) != floor(PV(m, at + P_FREE_K)) ||
            (PV(m, at + P_MOTOR) != 0 && !(PV(m, at + P_TAU_MOTOR) > 0)) ||
            (PV(m, at + P_OD) != 0 && !(PV(m, at + P_H_TAU) > 0)))
            c->err = TB_E_PAYLOAD;
        break;
    }
    case TB_KIND_AR: {
        uint32_t D = d[0], na = d[1], nb = d[2], nu = d[3];
        if (D > TB_MAX_POLY || na > TB_MAX_AR_ORDER || nb < 1 || nb > TB_MAX_AR_ORDER || nu < 1 || nu > 8) {
            c->err = TB_E_DIMS;
            return;
        }
        parse_sensors(c, m, 0);
        parse_geom(c, m);
        m->off[O_BODY] = take(c, 1); /* origin */
        take_val(c, 1, 1e7f, 0);     /* sample_s >= 1 s (seed 003: 600 s) */
        m->off[O_A] = c->pos;        /* terms: (column code 0 feed / 1 load, power > 0) */
        for (i = 0; i < nu && !c->err; i++) {
            take_int(c, 0, 1);
            take_val(c, 0, 16, 1);
        }
        m->off[O_B] = take(c, (D + 1) * na);
        m->off[O_C] = take(c, (D + 1) * nb * nu);
        m->off[O_D] = take(c, D + 1);
        break;
    }
    case TB_KIND_CLASSIFIER: {
        uint32_t K = d[0], nA = d[1], nB = d[2], nC = d[3], k;
        if (K < 1 || K > TB_MAX_CONDITIONS || nA < 1 || nA > TB_MAX_LEVELS || nB < 1 || nB > TB_MAX_LEVELS ||
            nC < 1 || nC > TB_MAX_LEVELS) {
            c->err = TB_E_DIMS;
            return;
        }
        if (!(PV(m, 0) > 0)) { c->err = TB_E_PAYLOAD; return; }
        m->off[O_BODY] = c->pos;
        take_val(c, 0, 1e6f, 1);     /* window_s */
        take_val(c, 1e-3f, 1e6f, 0); /* step_s */
        if (!c->err && PV(m, m->off[O_BODY] + 1) < PV(m, 0)) c->err = TB_E_PAYLOAD; /* step >= the period */
        take_val(c, 0, 1e6f, 0); /* min_moving_s */
        if (!c->err && PV(m, m->off[O_BODY]) / PV(m, 0) > (tb_real)TB_MAX_WINDOW) c->err = TB_E_DIMS;
        m->off[O_A] = take(c, nA + nB + nC);
        for (i = 0; i < nA + nB + nC && !c->err; i++) {
            uint32_t first = i == 0 || i == nA || i == nA + nB;
            if (!first && !(PV(m, m->off[O_A] + i) > PV(m, m->off[O_A] + i - 1))) c->err = TB_E_PAYLOAD;
        }
        m->off[O_B] = c->pos;
        for (k = 0; k < K && !c->err; k++) {
            take_int(c, 0, nA - 1);
            take_int(c, 0, nB - 1);
            take_int(c, 0, nC - 1);
        }
        m->n_sensors = 0;
        break;
    }
    case TB_KIND_LUMPED: {
        uint32_t n = d[0], S = d[1], K = d[2], A = d[3], src, ch, j;
        if (n < 1 || n > TB_MAX_LUMPED_NODES || S > TB_MAX_SENSORS || K > S || A > 1 || A > S) {
            c->err = TB_E_DIMS;
            return;
        }
        if (K > 0 && !(PV(m, 0) > 0)) { c->err = TB_E_PAYLOAD; return; } /* the terms' history needs the period */
        parse_sensors(c, m, S);
        parse_geom(c, m);
        m->off[O_BODY] = c->pos;
        src = take_int(c, 0, LU_SRC_CHANNEL);
        ch = take_int(c, 0, TB_MAX_SENSORS * 4u);
        take_int(c, 0, 1);                          /* u_nonneg */
        take_pair(c, TB_MIN_LUMPED_STEP_S, 1e6, 0); /* step_s */
        take_pair(c, 0, 1e30, 1);                   /* u_ref > 0 */
        take_pair(c, 0, 16, 1);                     /* exponent > 0 */
        m->off[O_A] = c->pos;
        for (i = 0; i < n && !c->err; i++) {
            take(c, 2 * i);           /* A_d[i][0..i-1] */
            take_pair(c, 0, 1, 0);    /* A_d[i][i] = exp(-step / tau_i) */
        }
        m->off[O_B] = take(c, 2 * n);
        m->off[O_C] = take(c, 2 * n);
        m->off[O_D] = c->pos;
        if (A) {
            take_int(c, 0, S - 1);
            take_pair(c, 0, 1, 0); /* exp(-step / tau_a) */
            take(c, 2);
        }
        m->off[O_E] = c->pos;
        for (j = 0; j < K && !c->err; j++) take_int(c, 0, S - 1);
        take(c, 2 * K);
        m->off[O_F] = take(c, 2);
        if (c->err) return;
        if (src != LU_SRC_CHANNEL && ch != 0) c->err = TB_E_PAYLOAD;
        if (src == LU_SRC_CHANNEL) {
            for (j = 0; j < S; j++) /* a temperature channel read as the operating input */
                if ((uint32_t)PV(m, m->off[O_SENS] + j) == ch) c->err = TB_E_PAYLOAD;
            if (ch + 1u > m->max_channel) m->max_channel = ch + 1u;
        }
        if (!c->err && lump_hist_samples(m) > (double)TB_MAX_WINDOW) c->err = TB_E_DIMS;
        break;
    }
    default:
        c->err = TB_E_KIND;
    }
}

/* ------------------------------------------------------- kind states */
typedef struct { /* GRU: ring of dT at the sample period */
    uint32_t cap, n, head;
    double t_first; /* time of the oldest sample in the ring */
    float *ring;    /* cap x S */
} gru_t;

typedef struct {
    uint32_t n, per_step;
    int have_t0, pending_snap;
    double t0, prev_t, ta0;
    tb_real prev_x, prev_f, prev_load, prev_amb; /* previous sample (filtered ambient rise) */
    uint64_t j;        /* next fine step */
    uint64_t k;        /* macro steps done */
    tb_real motor_y;   /* motor heat lag state */
    tb_real housing_y; /* fixed-bearing housing lag state (origin drift) */
    tb_real *theta, *q_nut, *h_cov, *diag, *rhs, *y1, *y2, *cp;
    tb_real h_sum, qb_sum, dta_sum, v_sum, motor_sum, free_sum;
    /* snapshots of the compensation table (seed 000 §4.3) at the last two step boundaries */
    int n_snap;
    double snap_t[2];
    tb_real snap_amb[2], snap_off[2];
    tb_real *snap_u; /* 2 x (n + 1) */
    int snap_cur;
    tb_real theta_b_local; /* housing input: fixed-end temperature at the step start */
    tb_real amb_b_start;   /* ambient rise at the step start */
} phys_t;

typedef struct {
    double t0, edge_lo; /* current interval [edge_lo, edge_hi) */
    uint64_t k;        /* intervals closed */
    int started;
    tb_real *usum;     /* nu */
    uint32_t ucount;
    double last_t;
    tb_real *last_v;   /* nu */
    tb_real *c_hist;   /* (na + 1) x (D + 1): c(k), c(k-1), ... newest first */
    tb_real *u_hist;   /* nb x nu: u(k), u(k-1), ... newest first */
    double g_t[2];
    tb_real *g_c;      /* 2 x (D + 1): c at the last two grid points */
    int g_n, g_cur;
} ar_t;

typedef struct {
    uint32_t cap, n, head; /* ring of samples: t (float, relative), x, f (<0: not moving) */
    float *rt, *rx, *rf;
    double t0;
    int have_t0;
    uint64_t g_next;       /* next grid index to classify */
    double last_t, period;
    int have_prev;
    /* labels of the last grid points (held) */
    double lab_t[4];
    int32_t lab[4];
    uint32_t lab_n, lab_head;
    int32_t held;
    float *scratch;        /* 2 x TB_MAX_FEEDS: distinct feeds of the window and their levels */
} clf_t;

typedef struct { /* lumped network (docs/concepts.md, physics_spindle) */
    uint32_t ns;           /* states per grid point: n nodes (+ 1: the lagged ambient rise) */
    uint32_t g_cap, r_cap; /* grid points kept; sensor-term samples kept */
    int started;
    double t0;             /* the grid starts at the run's first process sample */
    double acc_t;          /* the current interval [t0 + k step, ...) is integrated up to acc_t */
    uint64_t k;            /* intervals closed: the newest grid state is the one at t0 + k step */
    tb_real acc_q, acc_a;  /* integrals of the heat and of the ambient rise since t0 + k step */
    tb_real last_q, last_a; /* the last sample's heat and ambient rise, held to the next sample */
    tb_real *g;            /* g_cap x ns: grid state j in slot j % g_cap */
    double *r_t;           /* r_cap ring: sample times */
    tb_real *r_v;          /* r_cap ring: sum_j s_j dT_j at the sample (the unlagged sensor terms) */
    uint32_t r_n, r_head;
} lump_t;

static size_t floats_for_window(double window_s, double period_s)
{
    double n = ceil(window_s / period_s - 1e-9);
    return (size_t)n + 4u;
}

static void kind_carve(const tb_model *m, arena_t *a, void **ks)
{
    const uint32_t *d = m->dims;
    *ks = 0;
    switch (m->kind) {
    case TB_KIND_GRU: {
        gru_t *g = (gru_t *)carve(a, sizeof(gru_t));
        size_t cap = floats_for_window((double)d[3] * (double)PV(m, m->off[O_BODY]), (double)PV(m, 0));
        float *r = (float *)carve(a, sizeof(float) * cap * d[0]);
        if (a->p && !a->err) {
            memset(g, 0, sizeof *g);
            g->cap = (uint32_t)cap;
            g->ring = r;
        }
        *ks = g;
        break;
    }
    case TB_KIND_PHYSICS: {
        uint32_t n = d[1];
        phys_t *p = (phys_t *)carve(a, sizeof(phys_t));
        tb_real *arr = (tb_real *)carve(a, sizeof(tb_real) * (6u * n + 4u * (n + 1u)));
        if (a->p && !a->err) {
            memset(p, 0, sizeof *p);
            memset(arr, 0, sizeof(tb_real) * (6u * n + 4u * (n + 1u)));
            p->n = n;
            p->per_step = (uint32_t)PV(m, m->off[O_BODY] + P_PER_STEP);
            p->theta = arr;
            p->diag = arr + n;
            p->rhs = arr + 2 * n;
            p->y1 = arr + 3 * n;
            p->y2 = arr + 4 * n;
            p->cp = arr + 5 * n;
            p->q_nut = arr + 6 * n;           /* n + 1 */
            p->h_cov = arr + 7 * n + 1;       /* n + 1 */
            p->snap_u = arr + 8 * n + 2;      /* 2 (n + 1) */
        }
        *ks = p;
        break;
    }
    case TB_KIND_AR: {
        uint32_t D1 = d[0] + 1, na = d[1], nb = d[2], nu = d[3];
        ar_t *r = (ar_t *)carve(a, sizeof(ar_t));
        tb_real *arr = (tb_real *)carve(a, sizeof(tb_real) * (2u * nu + (na + 1u) * D1 + nb * nu + 2u * D1));
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
        break;
    }
    case TB_KIND_LUMPED: {
        uint32_t ns = d[0] + d[3], gcap = lump_grid_cap(m), rcap = (uint32_t)lump_hist_samples(m);
        lump_t *L = (lump_t *)carve(a, sizeof(lump_t));
        tb_real *g = (tb_real *)carve(a, sizeof(tb_real) * gcap * ns);
        double *rt = (double *)carve(a, sizeof(double) * (rcap ? rcap : 1u));
        tb_real *rv = (tb_real *)carve(a, sizeof(tb_real) * (rcap ? rcap : 1u));
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
        break;
    }
    case TB_KIND_CLASSIFIER: {
        clf_t *k = (clf_t *)carve(a, sizeof(clf_t));
        size_t cap = floats_for_window((double)PV(m, m->off[O_BODY]), (double)PV(m, 0));
        float *arr = (float *)carve(a, sizeof(float) * (3u * cap + 2u * TB_MAX_FEEDS));
        if (a->p && !a->err) {
            memset(k, 0, sizeof *k);
            k->cap = (uint32_t)cap;
            k->rt = arr;
            k->rx = arr + cap;
            k->rf = arr + 2 * cap;
            k->scratch = arr + 3 * cap;
            k->held = -1;
        }
        *ks = k;
        break;
    }
    default:
        break;
    }
}

static size_t layout(const tb_model *m, void *arena, size_t bytes, state_t **st_out)
{
    arena_t a;
    state_t *st;
    a.p = (uint8_t *)arena;
    a.used = 0;
    a.cap = arena ? bytes : (size_t)-1;
    a.err = 0;
    st = (state_t *)carve(&a, sizeof(state_t));
    if (m->kind == TB_KIND_CLASSIFIER) {
        void *ks;
        kind_carve(m, &a, &ks);
        if (arena && !a.err) {
            st->cm = 0;
            st->ks = ks;
        }
    } else {
        common_t *cm;
        void *ks;
        common_carve(m, &a, &cm, m->n_sensors);
        if (arena && !a.err) {
            cm->period_s = (double)PV(m, 0);
        }
        kind_carve(m, &a, &ks);
        if (arena && !a.err) {
            st->cm = cm;
            st->ks = ks;
        }
    }
    if (a.err) return 0;
    if (st_out) *st_out = st;
    return a.used;
}

size_t tb_model_arena_bytes(const tb_model *m)
{
    if (!m || !m->payload) return 0;
    return layout(m, 0, 0, 0);
}

int tb_model_start(tb_model *m, void *arena, size_t arena_bytes)
{
    state_t *st = 0;
    size_t need;
    if (!m || !m->payload || !arena) return TB_E_STATE;
    if (((uintptr_t)arena) % 8u != 0) return TB_E_ARENA;
    need = tb_model_arena_bytes(m);
    if (need == 0 || need > arena_bytes) return TB_E_ARENA;
    memset(arena, 0, need);
    if (layout(m, arena, arena_bytes, &st) == 0) return TB_E_ARENA;
    m->state = st;
    m->state_bytes = need;
    return TB_OK;
}

/* ----------------------------------------------------------- physics */
#define PP(m, i) PV(m, (m)->off[O_BODY] + (i))

static void phys_snapshot(const tb_model *m, phys_t *p, double t_b, tb_real dta_b)
{
    uint32_t i, n = p->n;
    int s = p->n_snap == 0 ? 0 : 1 - p->snap_cur;
    tb_real *u = p->snap_u + (size_t)s * (n + 1);
    tb_real alpha = PP(m, P_ALPHA), dx = PP(m, P_DX);
    u[0] = 0;
    for (i = 0; i < n; i++) u[i + 1] = u[i] + alpha * (p->theta[i] - dta_b) * dx * (tb_real)1e6;
    if (PP(m, P_FF) != 0) { /* seed 004 fixed-fixed: a fraction kappa of the free elongation suppressed */
        tb_real end = u[n], kappa = PP(m, P_KAPPA);
        for (i = 0; i <= n; i++) u[i] -= kappa * end * ((tb_real)i / (tb_real)n);
    }
    p->snap_t[s] = t_b;
    p->snap_amb[s] = dta_b;
    p->snap_off[s] = PP(m, P_OD) != 0 ? PP(m, P_BETA) * p->housing_y : 0;
    p->snap_cur = s;
    if (p->n_snap < 2) p->n_snap++;
}

static void solve_tridiag(uint32_t n, const tb_real *diag, tb_real off, const tb_real *rhs, tb_real *out,
                          tb_real *cprime)
{
    uint32_t i;
    tb_real b0 = diag[0];
    cprime[0] = off / b0;
    out[0] = rhs[0] / b0;
    for (i = 1; i < n; i++) {
        tb_real mm = diag[i] - off * cprime[i - 1];
        cprime[i] = off / mm;
        out[i] = (rhs[i] - off * out[i - 1]) / mm;
    }
    for (i = n - 1; i-- > 0;) out[i] -= cprime[i] * out[i + 1];
}

/* the parameters the hot loops use, decoded once per call (payload reads cannot be hoisted
 * by the compiler: the payload is bytes, which may alias the state) */
typedef struct {
    uint32_t n, nb, free_k;
    int motor, free_end, load, od, amb_mode;
    double dt, macro;
    tb_real dx, half, L, pf, sign, per_node, k1, k2, k3, k4, k5, k6, kF, kmotor, a_motor;
    tb_real cap, cond, side, end, bear_len, h_tau, h_gain_w, h_gain_v, h_coupling;
} phys_par_t;

static void phys_params(const tb_model *m, const phys_t *p, phys_par_t *q)
{
    q->n = p->n;
    q->nb = (uint32_t)PP(m, P_NB);
    q->macro = (double)PP(m, P_MACRO);
    q->dt = q->macro / (double)p->per_step; /* as dt_s in Python */
    q->dx = PP(m, P_DX);
    q->half = PP(m, P_NUT_LEN) / 2;
    q->L = PP(m, P_L);
    q->pf = PP(m, P_PF);
    q->sign = q->pf <= 0 ? 1 : -1;
    q->per_node = q->dx / PP(m, P_NUT_LEN);
    q->k1 = PP(m, P_K1);
    q->k2 = PP(m, P_K2);
    q->k3 = PP(m, P_K3);
    q->k4 = PP(m, P_K4);
    q->k5 = PP(m, P_K5);
    q->load = PP(m, P_LOAD) != 0;
    q->k6 = PP(m, P_K6);
    q->free_end = PP(m, P_FREE) != 0;
    q->kF = PP(m, P_KF);
    q->free_k = q->free_end ? (uint32_t)PP(m, P_FREE_K) : 0; /* validated only when present */
    q->motor = PP(m, P_MOTOR) != 0;
    q->kmotor = PP(m, P_KMOTOR);
    q->a_motor = q->motor ? (tb_real)exp(-q->dt / (double)PP(m, P_TAU_MOTOR)) : 0;
    q->od = PP(m, P_OD) != 0;
    q->amb_mode = (int)PP(m, P_AMB_MODE);
    q->cap = PP(m, P_CAP);
    q->cond = PP(m, P_COND);
    q->side = PP(m, P_SIDE);
    q->end = PP(m, P_END);
    q->bear_len = PP(m, P_BEAR_LEN);
    q->h_tau = PP(m, P_H_TAU);
    q->h_gain_w = PP(m, P_H_GAIN_W);
    q->h_gain_v = PP(m, P_H_GAIN_V);
    q->h_coupling = PP(m, P_H_COUPLING);
}

/* one macro step: step averages -> SDIRK2 (the same scheme as thermbench.sim.kernels.macro_run);
 * the nut heat and cover arrive as difference arrays (thermbench.sim.kernels.accumulate_step_averages) */
static void phys_macro(const phys_par_t *c, phys_t *p)
{
    uint32_t i, n = c->n, nb = c->nb;
    tb_real inv = (tb_real)1 / (tb_real)p->per_step;
    tb_real h_mean = p->h_sum * inv, qb_mean = p->qb_sum * inv, ta = p->dta_sum * inv;
    tb_real gamma = (tb_real)(1.0 - sqrt(2.0) / 2.0), gh = gamma * (tb_real)c->macro, off = -gh * c->cond;
    tb_real c1 = (1 - gamma) / gamma, qa = 0, ha = 0;
    tb_real *q = p->q_nut, *g = p->h_cov; /* difference arrays in, step averages out (in place) */
    for (i = 0; i < n; i++) {
        tb_real area = c->side + (i == n - 1 ? c->end : 0);
        if (i < nb) area = 0;
        qa += q[i];
        ha += g[i];
        q[i] = qa * inv;
        if (i < nb) q[i] += qb_mean * c->dx / c->bear_len;
        g[i] = (h_mean - ha * inv) * area;
    }
    if (c->motor) q[0] += p->motor_sum * inv;
    if (c->free_end)
        for (i = n - c->free_k; i < n; i++) q[i] += p->free_sum * inv * ((tb_real)1 / (tb_real)c->free_k);
    for (i = 0; i < n; i++) {
        tb_real nbh = (i == 0 || i == n - 1) ? 1 : 2;
        p->diag[i] = c->cap + gh * (nbh * c->cond + g[i]);
        p->rhs[i] = c->cap * p->theta[i] + gh * (q[i] + g[i] * ta);
    }
    solve_tridiag(n, p->diag, off, p->rhs, p->y1, p->cp);
    for (i = 0; i < n; i++) p->rhs[i] = c->cap * (p->theta[i] + c1 * (p->y1[i] - p->theta[i])) + gh * (q[i] + g[i] * ta);
    solve_tridiag(n, p->diag, off, p->rhs, p->y2, p->cp);
    for (i = 0; i < n; i++) p->theta[i] = p->y2[i];
    if (c->od) { /* fixed-bearing housing, first-order lag over the macro step */
        tb_real a = (tb_real)exp(-c->macro / (double)c->h_tau);
        tb_real u = c->h_gain_w * qb_mean + c->h_gain_v * (p->v_sum * inv) + c->h_coupling * p->theta_b_local + p->amb_b_start;
        p->housing_y = a * p->housing_y + (1 - a) * u;
    }
    for (i = 0; i <= n; i++) {
        q[i] = 0;
        g[i] = 0;
    }
    p->h_sum = p->qb_sum = p->dta_sum = p->v_sum = p->motor_sum = p->free_sum = 0;
    p->k++;
}

static tb_real phys_ambient_rise(const tb_model *m, const phys_t *p, double t, tb_real meas_rise)
{
    tb_real mode = PP(m, P_AMB_MODE);
    if (mode == 1) return meas_rise;
    if (mode == 2) {
        double w = 2.0 * 3.14159265358979323846 / (double)PP(m, P_AMB_PERIOD), tt = t - p->t0;
        double ph = (double)PP(m, P_AMB_PHASE);
        return (tb_real)((double)PP(m, P_AMB_AMP) * (sin(w * (tt + ph)) - sin(w * ph)) +
                         (double)PP(m, P_AMB_RATE) * tt / 3600.0);
    }
    return 0;
}

/* add value x cover to the difference array d (thermbench.sim.kernels._add_cover) */
static void add_cover(tb_real *d, int64_t lo, int64_t hi, tb_real w_lo, tb_real w_hi, tb_real v)
{
    d[lo] += v;
    d[hi + 1] -= v;
    d[lo] -= v * (1 - w_lo);
    d[lo + 1] += v * (1 - w_lo);
    if (hi != lo) {
        d[hi] -= v * (1 - w_hi);
        d[hi + 1] += v * (1 - w_hi);
    }
}

/* fine steps with times <= t_hi (inclusive), values interpolated from the previous sample to
 * (t_hi, x, f, load, amb) as numpy.interp over the log; stops at j_stop */
static void phys_fine(const tb_model *m, phys_t *p, double t_hi, tb_real x1, tb_real f1, tb_real l1, tb_real a1,
                      uint64_t j_stop)
{
    phys_par_t c;
    double span = t_hi - p->prev_t;
    tb_real sx, sf, sl, sa;
    phys_params(m, p, &c);
    /* the slopes of numpy.interp between the previous sample and this one, computed once */
    sx = span > 0 ? (x1 - p->prev_x) / (tb_real)span : 0;
    sf = span > 0 ? (f1 - p->prev_f) / (tb_real)span : 0;
    sl = span > 0 ? (l1 - p->prev_load) / (tb_real)span : 0;
    sa = span > 0 ? (a1 - p->prev_amb) / (tb_real)span : 0;
    for (;;) {
        double tf = p->t0 + (double)p->j * c.dt;
        tb_real axis, v, load, amb, xs, h, qn, qb, a, b, u;
        if (p->j >= j_stop || tf > t_hi) break;
        if (p->pending_snap) break; /* the boundary ambient is not known yet */
        if (tf <= p->prev_t || span <= 0) {
            u = 0;
        } else {
            u = (tb_real)(tf - p->prev_t);
        }
        if (tf >= t_hi && span > 0) {
            axis = x1;
            v = (tb_real)fabs((double)f1);
            load = l1;
            amb = a1;
        } else {
            axis = p->prev_x + u * sx;
            v = (tb_real)fabs((double)(p->prev_f + u * sf));
            load = p->prev_load + u * sl;
            amb = p->prev_amb + u * sa;
        }
        if (c.amb_mode != 1) amb = phys_ambient_rise(m, p, tf, amb);
        if (p->j % p->per_step == 0) { /* step start: housing inputs */
            uint32_t i, nl = c.nb > 0 ? c.nb : 1;
            tb_real s0 = 0;
            if (c.od) {
                for (i = 0; i < nl && i < c.n; i++) s0 += p->theta[i];
                p->theta_b_local = s0 / (tb_real)nl;
            }
            p->amb_b_start = p->k == 0 ? 0 : p->snap_amb[p->snap_cur];
        }
        xs = c.sign * (axis / (tb_real)1000 - c.pf);
        if (xs < 0) xs = 0;
        if (xs > c.L) xs = c.L;
        h = c.k1 * v + c.k2;
        qb = c.k3 * v;
        qn = c.k4 * v + c.k5 * v * v;
        if (c.load) qn += c.k6 * load * v;
        /* nut cover (thermbench.sim.kernels._nut_cover) */
        a = xs - c.half;
        b = xs + c.half;
        if (a < (tb_real)c.nb * c.dx) a = (tb_real)c.nb * c.dx;
        if (b > (tb_real)c.n * c.dx) b = (tb_real)c.n * c.dx;
        if (b > a) {
            int64_t lo = floor_clamp((double)(a / c.dx), 0, (int64_t)c.n - 1);
            int64_t hi = floor_clamp((double)(b / c.dx), 0, (int64_t)c.n - 1);
            tb_real w_lo, w_hi;
            if (lo == hi) {
                w_lo = w_hi = (b - a) / c.dx;
            } else {
                w_lo = (tb_real)(lo + 1) - a / c.dx;
                w_hi = b / c.dx - (tb_real)hi;
            }
            add_cover(p->q_nut, lo, hi, w_lo, w_hi, qn * c.per_node);
            add_cover(p->h_cov, lo, hi, w_lo, w_hi, h);
        }
        p->h_sum += h;
        p->qb_sum += qb;
        p->dta_sum += amb;
        p->v_sum += v;
        if (c.motor) {
            p->motor_sum += c.kmotor * p->motor_y;
            p->motor_y = c.a_motor * p->motor_y + (1 - c.a_motor) * v;
        }
        if (c.free_end) p->free_sum += c.kF * v;
        p->j++;
        if (p->j % p->per_step == 0) {
            phys_macro(&c, p);
            p->pending_snap = 1;
        }
        if (p->pending_snap) {
            double t_b = p->t0 + (double)p->k * c.macro;
            if (t_b <= t_hi) {
                tb_real amb_b = phys_ambient_rise(m, p, t_b, (tb_real)interp1(t_b, p->prev_t, t_hi, p->prev_amb, a1));
                phys_snapshot(m, p, t_b, amb_b);
                p->pending_snap = 0;
            }
        }
    }
}

static void phys_sample(const tb_model *m, phys_t *p, const motion_t *mo, const tb_real *dT)
{
    tb_real amb = m->n_sensors ? dT[0] : 0;
    if (!p->have_t0) {
        p->have_t0 = 1;
        p->t0 = mo->t_s;
        p->prev_t = mo->t_s;
        p->prev_x = (tb_real)mo->axis_mm;
        p->prev_f = (tb_real)mo->feed_mm_min;
        p->prev_load = (tb_real)mo->load_N;
        p->prev_amb = amb;
        phys_snapshot(m, p, mo->t_s, phys_ambient_rise(m, p, mo->t_s, amb)); /* theta = 0 at t0 */
    }
    if (p->pending_snap) { /* the boundary of the last step lies before this sample */
        double t_b = p->t0 + (double)p->k * (double)PP(m, P_MACRO);
        if (t_b <= mo->t_s) {
            tb_real amb_b = phys_ambient_rise(
                m, p, t_b, (tb_real)interp1(t_b, p->prev_t, mo->t_s, p->prev_amb, amb));
            phys_snapshot(m, p, t_b, amb_b);
            p->pending_snap = 0;
        }
    }
    phys_fine(m, p, mo->t_s, (tb_real)mo->axis_mm, (tb_real)mo->feed_mm_min, (tb_real)mo->load_N, amb,
              (uint64_t)-1);
    p->prev_t = mo->t_s;
    p->prev_x = (tb_real)mo->axis_mm;
    p->prev_f = (tb_real)mo->feed_mm_min;
    p->prev_load = (tb_real)mo->load_N;
    p->prev_amb = amb;
}

static void phys_finish(const tb_model *m, phys_t *p)
{
    /* thermbench integrates ceil(span / macro) whole steps, the log's last values held */
    double span = p->prev_t - p->t0, macro = (double)PP(m, P_MACRO);
    uint64_t steps = (uint64_t)-floor_clamp(-(span / macro - 1e-9), -((int64_t)1 << 40), 0), j_stop; /* ceil */
    if (!p->have_t0) return;
    if (steps < 1) steps = 1;
    j_stop = steps * p->per_step;
    while ((p->j < j_stop && !p->pending_snap) || p->pending_snap) {
        double t_far = p->t0 + (double)(p->j + 1) * (macro / (double)p->per_step) + macro;
        if (p->pending_snap) {
            double t_b = p->t0 + (double)p->k * macro;
            phys_snapshot(m, p, t_b, phys_ambient_rise(m, p, t_b, p->prev_amb));
            p->pending_snap = 0;
            continue;
        }
        /* past the log: every value held (prev sample repeated) */
        phys_fine(m, p, t_far, p->prev_x, p->prev_f, p->prev_load, p->prev_amb, j_stop);
        p->prev_t = t_far; /* interpolation between equal values is the held value */
    }
}

static int phys_predict(const tb_model *m, const phys_t *p, double t, double axis_mm, tb_real *thermal)
{
    int a, b;
    double w;
    tb_real pf = PP(m, P_PF), sign = pf <= 0 ? 1 : -1, L = PP(m, P_L), dx = PP(m, P_DX);
    tb_real x, nodes, f, tem, dta, tea, off;
    int64_t mi;
    const tb_real *ua, *ub;
    uint32_t n = p->n;
    if (p->n_snap == 0) return TB_E_NOTREADY;
    b = p->snap_cur;
    a = p->n_snap == 2 ? 1 - b : b;
    if (p->n_snap == 2 && t < p->snap_t[a]) return TB_E_LATE;
    w = (p->n_snap == 2 && p->snap_t[b] > p->snap_t[a]) ? (t - p->snap_t[a]) / (p->snap_t[b] - p->snap_t[a]) : 1.0;
    if (w < 0) w = 0;
    if (w > 1) w = 1;
    x = sign * ((tb_real)axis_mm / (tb_real)1000 - pf);
    if (x < 0) x = 0;
    if (x > L) x = L;
    nodes = x / dx;
    mi = floor_clamp((double)nodes, 0, (int64_t)n - 1);
    if (mi < 0) mi = 0;
    if (mi > (int64_t)n - 1) mi = (int64_t)n - 1;
    f = nodes - (tb_real)mi;
    ua = p->snap_u + (size_t)a * (n + 1);
    ub = p->snap_u + (size_t)b * (n + 1);
    tem = (ua[mi] * (1 - f) + ua[mi + 1] * f) * (tb_real)(1 - w) + (ub[mi] * (1 - f) + ub[mi + 1] * f) * (tb_real)w;
    dta = p->snap_amb[a] * (tb_real)(1 - w) + p->snap_amb[b] * (tb_real)w;
    tea = PP(m, P_ALPHA) * dta * (tb_real)axis_mm * (tb_real)1e-3 * (tb_real)1e6;
    off = p->snap_off[a] * (tb_real)(1 - w) + p->snap_off[b] * (tb_real)w;
    *thermal = sign * (tem + tea) + off;
    return TB_OK;
}

/* ----------------------------------------------------------------- AR */
static tb_real ar_term(const tb_model *m, uint32_t i, const motion_t *mo)
{
    tb_real code = PV(m, m->off[O_A] + 2 * i), power = PV(m, m->off[O_A] + 2 * i + 1);
    tb_real v = code == 0 ? (tb_real)mo->feed_mm_min : (tb_real)mo->load_N;
    return power == 1 ? v : (tb_real)pow((double)v, (double)power);
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
            if (r->k >= (uint64_t)b + 1)
                for (q = 0; q < nu; q++) acc += PV(m, m->off[O_C] + (i * nb + b) * nu + q) * r->u_hist[b * nu + q];
        cnew[i] = acc;
    }
    for (a = na; a-- > 1;)
        for (i = 0; i < D1; i++) r->c_hist[a * D1 + i] = r->c_hist[(a - 1) * D1 + i];
    if (na > 0)
        for (i = 0; i < D1; i++) r->c_hist[i] = cnew[i];
    r->g_cur = 1 - r->g_cur;
    r->g_t[r->g_cur] = r->t0 + (double)r->k * (double)PV(m, m->off[O_BODY] + 1);
    for (i = 0; i < D1; i++) r->g_c[r->g_cur * D1 + i] = cnew[i];
    if (r->g_n < 2) r->g_n++;
}

static void ar_sample(const tb_model *m, ar_t *r, const motion_t *mo, int final)
{
    uint32_t nu = m->dims[3], q;
    double dt = (double)PV(m, m->off[O_BODY] + 1);
    tb_real v[8] = {0}, u[8] = {0};
    if (final) {
        /* thermbench simulates ceil(span / sample_s) intervals; the last one may be partial */
        uint64_t total;
        if (!r->started) return;
        total = (uint64_t)-floor_clamp(-((r->last_t - r->t0) / dt - 1e-9), -((int64_t)1 << 40), 0); /* ceil */
        if (total < 1) total = 1;
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
        double hi = r->t0 + (double)(r->k + 1) * dt;
        if (mo->t_s < hi) break;
        if (r->ucount > 0) {
            for (q = 0; q < nu; q++) u[q] = r->usum[q] / (tb_real)r->ucount;
        } else { /* no sample inside: the value interpolated at its middle */
            double mid = r->t0 + ((double)r->k + 0.5) * dt;
            for (q = 0; q < nu; q++) u[q] = (tb_real)interp1(mid, r->last_t, mo->t_s, r->last_v[q], v[q]);
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

static int ar_predict(const tb_model *m, const ar_t *r, double t, double axis_mm, tb_real *thermal)
{
    uint32_t D1 = m->dims[0] + 1, i;
    int a, b;
    tb_real acc = 0, pw = 1, x = (tb_real)axis_mm - PV(m, m->off[O_BODY]);
    if (!r->started) return TB_E_NOTREADY;
    b = r->g_cur;
    a = r->g_n == 2 ? 1 - b : b;
    if (r->g_n == 2 && t < r->g_t[a]) return TB_E_LATE;
    for (i = 0; i < D1; i++) {
        tb_real c = (tb_real)interp1(t, r->g_t[a], r->g_t[b], r->g_c[a * D1 + i], r->g_c[b * D1 + i]);
        acc += c * pw;
        pw *= x;
    }
    *thermal = acc;
    return TB_OK;
}

/* -------------------------------------------------------------- lumped */
/* docs/concepts.md, "A lumped thermal network for a spindle" (thermbench.models.lumped): the heat
 * q = (u/u_ref)^p of each sample is held to the next sample and averaged exactly over the intervals
 * of a grid of step_s from the run's first process sample; the chain advances one interval with the
 * exact discretisation theta' = A_d theta + B_d q (A_d lower triangular, from the file: no matrix
 * exponential here), the lagged ambient rise theta_a' = a theta_a + (1 - a) mean(dT_a); a query
 * interpolates the grid states linearly in time and adds the unlagged sensor terms at its time. */
typedef struct {
    uint32_t n, A, K, amb;
    double h;
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

/* the operating input of a sample (check_sample has made sure its channel is there) */
static double lump_u(const tb_model *m, const tb_sample *s)
{
    uint32_t b = m->off[O_BODY];
    switch ((uint32_t)PV(m, b)) {
    case LU_SRC_FEED: return s->feed_mm_min;
    case LU_SRC_AXIS: return s->axis_mm;
    case LU_SRC_LOAD: return s->load_N;
    default: return s->temps_C[(uint32_t)PV(m, b + 1u)];
    }
}

/* is u a usable operating input? (a negative value to a fractional power: thermbench raises too) */
static int lump_check_u(const tb_model *m, double u)
{
    uint32_t b = m->off[O_BODY];
    double u_ref = (double)PV(m, b + 5u) + (double)PV(m, b + 6u);
    double p = (double)PV(m, b + 7u) + (double)PV(m, b + 8u), q;
    if (!isfinite(u) || fabs(u) > TB_MAX_OPERATING) return TB_E_INPUT;
    if (u < 0 && (PV(m, b + 2u) != 0 || p != floor(p))) return TB_E_INPUT;
    q = pow(u / u_ref, p);
    if (!isfinite(q) || fabs(q) > TB_MAX_HEAT) return TB_E_INPUT;
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
static void lump_integrate(const lump_par_t *c, lump_t *L, double t)
{
    for (;;) {
        double edge = L->t0 + (double)(L->k + 1u) * c->h;
        if (t < edge) break;
        L->acc_q += L->last_q * (tb_real)(edge - L->acc_t);
        L->acc_a += L->last_a * (tb_real)(edge - L->acc_t);
        lump_advance(c, LU_SLOT(L, L->k), L->acc_q / (tb_real)c->h, L->acc_a / (tb_real)c->h, LU_SLOT(L, L->k + 1u));
        L->k++;
        L->acc_q = L->acc_a = 0;
        L->acc_t = edge;
    }
    L->acc_q += L->last_q * (tb_real)(t - L->acc_t);
    L->acc_a += L->last_a * (tb_real)(t - L->acc_t);
    L->acc_t = t;
}

static void lump_sample(const tb_model *m, lump_t *L, const motion_t *mo, const tb_real *dT)
{
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
    L->last_q = (tb_real)pow((double)((tb_real)mo->op_u / c.u_ref), (double)c.p);
    L->last_a = c.A ? dT[c.amb] : 0;
    if (L->r_cap) {
        L->r_t[L->r_head] = mo->t_s;
        L->r_v[L->r_head] = rv;
        L->r_head = (L->r_head + 1u) % L->r_cap;
        if (L->r_n < L->r_cap) L->r_n++;
    }
}

static void lump_finish(const tb_model *m, lump_t *L)
{
    /* thermbench simulates ceil(span / step) whole intervals (at least one), the last value held */
    lump_par_t c;
    double span;
    uint64_t total;
    if (!L->started) return;
    lump_params(m, &c);
    span = L->acc_t - L->t0;
    total = (uint64_t)-floor_clamp(-(span / c.h - 1e-9), -((int64_t)1 << 40), 0); /* ceil */
    if (total < 1) total = 1;
    if (L->k < total) lump_integrate(&c, L, L->t0 + (double)total * c.h);
}

/* grid state k + ahead (ahead >= 1), before the samples that decide it: the current interval
 * completed with the last sample held, the later ones held throughout (exact once the log ended) */
static void lump_ahead(const lump_par_t *c, const lump_t *L, uint64_t ahead, tb_real *out)
{
    tb_real x[TB_MAX_LUMPED_NODES + 1u];
    double edge = L->t0 + (double)(L->k + 1u) * c->h;
    uint64_t i;
    uint32_t j;
    tb_real q = (L->acc_q + L->last_q * (tb_real)(edge - L->acc_t)) / (tb_real)c->h;
    tb_real ra = (L->acc_a + L->last_a * (tb_real)(edge - L->acc_t)) / (tb_real)c->h;
    lump_advance(c, LU_SLOT(L, L->k), q, ra, out);
    for (i = 1; i < ahead; i++) {
        for (j = 0; j < L->ns; j++) x[j] = out[j];
        lump_advance(c, x, L->last_q, L->last_a, out);
    }
}

/* the unlagged sensor terms at t, interpolated over the samples (numpy.interp over the log) */
static int lump_terms_at(const lump_t *L, double t, tb_real *out)
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
    *out = (tb_real)interp1(t, L->r_t[LU_R(lo)], L->r_t[LU_R(hi)], L->r_v[LU_R(lo)], L->r_v[LU_R(hi)]);
#undef LU_R
    return TB_OK;
}

static int lump_predict(const tb_model *m, const lump_t *L, double t, tb_real *thermal)
{
    lump_par_t c;
    tb_real xa[TB_MAX_LUMPED_NODES + 1u], xb[TB_MAX_LUMPED_NODES + 1u], out = 0, terms = 0;
    double pos;
    tb_real w;
    uint64_t kq, oldest;
    uint32_t i, gains = m->off[O_C];
    if (!L->started) return TB_E_NOTREADY;
    lump_params(m, &c);
    pos = (t - L->t0) / c.h;
    if (pos < 0) pos = 0; /* before the log: at rest (thermbench clips the grid position) */
    if (pos >= (double)L->k + (double)L->g_cap) return TB_E_NOTREADY;
    kq = (uint64_t)floor(pos);
    w = (tb_real)(pos - (double)kq);
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

/* ---------------------------------------------------------------- GRU */
static void gru_push(const tb_model *m, gru_t *g, double t, const tb_real *dT)
{
    uint32_t S = m->dims[0], j;
    double period = (double)PV(m, 0);
    if (g->n > 0) { /* samples missing in between (a dropped or rejected one): the values numpy.interp gives */
        uint32_t newest = (g->head + g->cap - 1) % g->cap, k, d;
        double t_new = g->t_first + (double)(g->n - 1) * period;
        d = (uint32_t)floor_clamp((t - t_new) / period + 0.5, 1, (int64_t)g->cap);
        for (k = 1; k < d; k++) {
            tb_real w = (tb_real)k / (tb_real)d;
            for (j = 0; j < S; j++) {
                tb_real v0 = (tb_real)g->ring[newest * S + j];
                g->ring[g->head * S + j] = (float)(v0 + w * (dT[j] - v0));
            }
            g->head = (g->head + 1) % g->cap;
            if (g->n < g->cap) g->n++;
            else g->t_first += period;
        }
    }
    if (g->n == 0) g->t_first = t;
    for (j = 0; j < S; j++) g->ring[g->head * S + j] = (float)dT[j];
    g->head = (g->head + 1) % g->cap;
    if (g->n < g->cap) g->n++;
    else g->t_first += period;
}

static tb_real sigm(tb_real x) { return (tb_real)(1.0 / (1.0 + exp(-(double)x))); }

static int gru_predict(const tb_model *m, const gru_t *g, double t, double axis_mm, tb_real *thermal)
{
    uint32_t S = m->dims[0], H = m->dims[1], D = m->dims[2], K = m->dims[3], j, i, k;
    uint32_t body = m->off[O_BODY];
    double step = (double)PV(m, body), period = (double)PV(m, 0);
    tb_real h[TB_MAX_GRU_HIDDEN], hn[TB_MAX_GRU_HIDDEN], x[TB_MAX_SENSORS];
    tb_real p, out = 0, pw = 1;
    uint32_t oldest = (g->head + g->cap - g->n) % g->cap;
    double t_newest;
    if (g->n == 0) return TB_E_NOTREADY;
    t_newest = g->t_first + (double)(g->n - 1) * period;
    for (j = 0; j < H; j++) h[j] = 0;
    for (k = K + 1; k-- > 0;) { /* oldest lag first */
        double tau = t - (double)k * step, pos;
        uint32_t i0, i1;
        double w;
        if (tau < g->t_first && g->n == g->cap) return TB_E_LATE;
        pos = (tau - g->t_first) / period;
        if (pos <= 0) { i0 = i1 = 0; w = 0; }
        else if (tau >= t_newest) { i0 = i1 = g->n - 1; w = 0; }
        else {
            i0 = (uint32_t)floor_clamp(pos, 0, (int64_t)g->n - 1);
            if (i0 >= g->n - 1) i0 = g->n - 2;
            i1 = i0 + 1;
            w = pos - (double)i0;
        }
        for (j = 0; j < S; j++) {
            tb_real v0 = (tb_real)g->ring[((oldest + i0) % g->cap) * S + j];
            tb_real v1 = (tb_real)g->ring[((oldest + i1) % g->cap) * S + j];
            tb_real v = v0 + (tb_real)w * (v1 - v0);
            x[j] = (v - PV(m, body + 1 + j)) / PV(m, body + 1 + S + j);
        }
        /* PyTorch GRU cell, gates (r, z, n) */
        for (i = 0; i < H; i++) {
            tb_real gi[3], gh[3];
            uint32_t gate;
            for (gate = 0; gate < 3; gate++) {
                uint32_t row = gate * H + i;
                tb_real si = PV(m, m->off[O_C] + row), sh = PV(m, m->off[O_D] + row);
                for (j = 0; j < S; j++) si += PV(m, m->off[O_A] + row * S + j) * x[j];
                for (j = 0; j < H; j++) sh += PV(m, m->off[O_B] + row * H + j) * h[j];
                gi[gate] = si;
                gh[gate] = sh;
            }
            {
                tb_real r = sigm(gi[0] + gh[0]), z = sigm(gi[1] + gh[1]);
                tb_real nn = (tb_real)tanh((double)(gi[2] + r * gh[2]));
                hn[i] = (1 - z) * nn + z * h[i];
            }
        }
        for (i = 0; i < H; i++) h[i] = hn[i];
    }
    p = ((tb_real)axis_mm - PV(m, body + 1 + 2 * S)) / PV(m, body + 2 + 2 * S);
    for (i = 0; i <= D; i++) {
        tb_real c = PV(m, m->off[O_F] + i);
        for (j = 0; j < H; j++) c += PV(m, m->off[O_E] + i * H + j) * h[j];
        out += c * pw;
        pw *= p;
    }
    *thermal = out * PV(m, body + 4 + 2 * S) + PV(m, body + 3 + 2 * S);
    return TB_OK;
}

/* ------------------------------------------------------------ MLP */
static tb_real act(uint32_t code, tb_real x)
{
    switch (code) {
    case ACT_TANH: return (tb_real)tanh((double)x);
    case ACT_RELU: return x > 0 ? x : 0;
    case ACT_GELU: return (tb_real)(0.5 * (double)x * (1.0 + erf((double)x / sqrt(2.0))));
    case ACT_SILU: return x * sigm(x);
    default: return sigm(x);
    }
}

static tb_real mlp_eval(const tb_model *m, const tb_real *dT, double axis_mm)
{
    uint32_t S = m->dims[0], L = m->dims[1], body = m->off[O_BODY], l, i, j, width = S + 1, at = m->off[O_B];
    tb_real a[TB_MAX_WIDTH], b[TB_MAX_WIDTH];
    for (j = 0; j < S; j++) a[j] = (dT[j] - PV(m, body + j)) / PV(m, body + S + 1 + j);
    a[S] = ((tb_real)axis_mm - PV(m, body + S)) / PV(m, body + 2 * S + 1);
    for (l = 0; l < L; l++) {
        uint32_t w = (uint32_t)PV(m, m->off[O_A] + l);
        for (i = 0; i < w; i++) {
            tb_real s = PV(m, at + w * width + i);
            for (j = 0; j < width; j++) s += PV(m, at + i * width + j) * a[j];
            b[i] = l + 1 < L ? act(m->dims[2], s) : s;
        }
        at += w * width + w;
        width = w;
        for (i = 0; i < w; i++) a[i] = b[i];
    }
    return a[0] * PV(m, body + 2 * S + 3) + PV(m, body + 2 * S + 2);
}

/* ------------------------------------------------------------ LSSVM */
static tb_real lssvm_eval(const tb_model *m, const tb_real *dT, double axis_mm)
{
    uint32_t S = m->dims[0], N = m->dims[1], d = S + 1, body = m->off[O_BODY], i, j;
    tb_real z[TB_MAX_SENSORS + 1], sigma2 = PV(m, body + 2 * d);
    tb_real acc = PV(m, body + 2 * d + 1) + PV(m, body + 2 * d + 2);
    tb_real inv2s = (tb_real)1 / (2 * sigma2);
    for (j = 0; j < S; j++) z[j] = (dT[j] - PV(m, body + j)) / PV(m, body + d + j);
    z[S] = ((tb_real)axis_mm - PV(m, body + S)) / PV(m, body + d + S);
    for (i = 0; i < N; i++) {
        tb_real d2 = 0;
        uint32_t at = m->off[O_B] + i * d;
        for (j = 0; j < d; j++) {
            tb_real e = z[j] - PV(m, at + j);
            d2 += e * e;
        }
        acc += (PV(m, m->off[O_A] + i) + PV(m, m->off[O_A] + N + i)) * (tb_real)exp(-(double)(d2 * inv2s));
    }
    return acc;
}

/* ------------------------------------------------------------ MLR */
static tb_real mlr_curve_eval(const tb_model *m, const tb_real *dT, double axis_mm)
{
    uint32_t S = m->dims[0], D = m->dims[1], body = m->off[O_BODY], i, j;
    tb_real x = (tb_real)axis_mm - PV(m, body), pw = 1, out = 0;
    for (i = 0; i <= D; i++) {
        uint32_t row = body + 1 + i * (S + 1);
        tb_real c = PV(m, row);
        for (j = 0; j < S; j++) c += PV(m, row + 1 + j) * dT[j];
        out += c * pw;
        pw *= x;
    }
    return out;
}

static tb_real mlr001_eval(const tb_model *m, const tb_real *dT, double axis_mm)
{
    uint32_t deg = m->dims[1], body = m->off[O_BODY], i;
    tb_real s = 0, pw = 1;
    for (i = 1; i <= deg; i++) {
        pw *= dT[0];
        s += PV(m, body + i) * pw;
    }
    s += PV(m, body + deg + 1) * dT[1] + PV(m, body + deg + 2);
    return s * ((tb_real)axis_mm - PV(m, body));
}

/* ------------------------------------------------------ classifier */
static void clf_levels_prob(const tb_model *m, uint32_t at, uint32_t nl, tb_real v, tb_real *p)
{
    uint32_t i;
    tb_real mx = 0, tot = 0;
    int hit = 0;
    for (i = 0; i < nl; i++)
        if (fabs((double)PV(m, at + i)) > (double)mx) mx = (tb_real)fabs((double)PV(m, at + i));
    if (mx < 1) mx = 1;
    for (i = 0; i < nl; i++) {
        tb_real d = (tb_real)fabs((double)(v - PV(m, at + i)));
        if (d <= (tb_real)1e-9 * mx) {
            p[i] = 1;
            hit = 1;
        } else {
            p[i] = 1 / d;
        }
    }
    for (i = 0; i < nl; i++) {
        tb_real d = (tb_real)fabs((double)(v - PV(m, at + i)));
        if (hit) p[i] = d <= (tb_real)1e-9 * mx ? 1 : 0;
        else tot += p[i];
    }
    if (!hit && tot > 0)
        for (i = 0; i < nl; i++) p[i] /= tot;
}

/* seed 002 eq. 15-19 on one motion (stroke A, position B = start + end, feed C) */
static int32_t clf_predict_one(const tb_model *m, tb_real A, tb_real B, tb_real C)
{
    uint32_t K = m->dims[0], nA = m->dims[1], nB = m->dims[2], nC = m->dims[3], k;
    tb_real pa[TB_MAX_LEVELS], pb[TB_MAX_LEVELS], pc[TB_MAX_LEVELS], best = -1;
    int32_t arg = 0;
    clf_levels_prob(m, m->off[O_A], nA, A, pa);
    clf_levels_prob(m, m->off[O_A] + nA, nB, B, pb);
    clf_levels_prob(m, m->off[O_A] + nA + nB, nC, C, pc);
    for (k = 0; k < K; k++) {
        uint32_t at = m->off[O_B] + 3 * k;
        tb_real s = pa[(uint32_t)PV(m, at)] + pb[(uint32_t)PV(m, at + 1)] + pc[(uint32_t)PV(m, at + 2)] + (tb_real)1 / (tb_real)K;
        if (s > best) {
            best = s;
            arg = (int32_t)k;
        }
    }
    return arg;
}

/* ring index i (0 = oldest) */
#define RI(k, i) (((k)->head + (k)->cap - (k)->n + (i)) % (k)->cap)

/* features of the window (T - window, T] (thermbench.classify.window_features, with the feed
 * levels clustered over the window and its two neighbour samples); returns the raw label or -1 */
static int32_t clf_window(const tb_model *m, clf_t *k, double T)
{
    uint32_t body = m->off[O_BODY], i, nlev = 0, nu = 0, lo = (uint32_t)-1, hi = 0, a, b;
    double window = (double)PV(m, body), min_moving = (double)PV(m, body + 2), period = k->period;
    float *u = k->scratch, *lev = k->scratch + TB_MAX_FEEDS;
    tb_real time_in[TB_MAX_FEEDS], feed_in[TB_MAX_FEEDS], x0 = 0, x1 = 0, total = 0;
    uint32_t dom = 0;
    int found = 0;
    memset(time_in, 0, sizeof time_in);
    memset(feed_in, 0, sizeof feed_in);
    if (k->n == 0) return -1;
    for (i = 0; i < k->n; i++) {
        double t = k->t0 + (double)k->rt[RI(k, i)];
        if (t > T - window && t <= T) {
            if (lo == (uint32_t)-1) lo = i;
            hi = i + 1;
        }
    }
    if (lo == (uint32_t)-1) return -1;
    /* distinct moving feeds of the window and its neighbours, sorted */
    a = lo > 0 ? lo - 1 : lo;
    b = hi < k->n ? hi + 1 : hi;
    for (i = a; i < b; i++) {
        float f = k->rf[RI(k, i)];
        uint32_t j, q;
        if (!(f > 0)) continue;
        for (j = 0; j < nu && u[j] < f; j++) {}
        if (j < nu && u[j] == f) continue;
        if (nu == TB_MAX_FEEDS) return -2; /* more distinct feeds than the runtime clusters */
        for (q = nu; q > j; q--) u[q] = u[q - 1];
        u[j] = f;
        nu++;
    }
    if (nu == 0) return -1;
    /* chain clustering within 1 % (thermbench.classify._cluster_feeds): lev[j] = level of u[j] */
    {
        uint32_t j;
        lev[0] = 0;
        for (j = 1; j < nu; j++) {
            if ((tb_real)u[j] - (tb_real)u[j - 1] > (tb_real)0.01 * (tb_real)u[j]) nlev++;
            lev[j] = (float)nlev;
        }
        nlev++;
    }
    for (i = 0; i < nlev; i++) time_in[i] = feed_in[i] = 0;
    for (i = lo; i < hi; i++) {
        float f = k->rf[RI(k, i)];
        double w;
        int32_t c;
        if (!(f > 0)) continue;
        if (i + 1 < k->n) w = (double)k->rt[RI(k, i + 1)] - (double)k->rt[RI(k, i)];
        else w = period;
        {
            uint32_t j;
            for (j = 0; j < nu && u[j] != f; j++) {}
            c = (int32_t)lev[j];
        }
        time_in[c] += (tb_real)w;
        feed_in[c] += (tb_real)(w * (double)f);
        total += (tb_real)w;
    }
    for (i = 1; i < nlev; i++)
        if (time_in[i] > time_in[dom]) dom = i;
    if (!((double)total >= min_moving) || !(time_in[dom] > 0)) return -1;
    /* stroke range at the dominant feed */
    for (i = lo; i < hi; i++) {
        float f = k->rf[RI(k, i)];
        uint32_t j;
        tb_real x = (tb_real)k->rx[RI(k, i)];
        if (!(f > 0)) continue;
        for (j = 0; j < nu && u[j] != f; j++) {}
        if ((uint32_t)lev[j] != dom) continue;
        if (!found) { x0 = x1 = x; found = 1; }
        if (x < x0) x0 = x;
        if (x > x1) x1 = x;
    }
    {
        /* turning points between samples (1 Hz aliasing), see window_features */
        tb_real up = x1, down = x0, tol = (tb_real)1e-6;
        int32_t cprev, c0, c1n, c2;
        {
            tb_real mx = 1;
            if (fabs((double)x0) > (double)mx) mx = (tb_real)fabs((double)x0);
            if (fabs((double)x1) > (double)mx) mx = (tb_real)fabs((double)x1);
            tol = (tb_real)1e-6 * mx;
        }
        for (i = lo; i + 1 < hi; i++) {
            float fa = k->rf[RI(k, i)];
            double dt, L, gap;
            tb_real xa, xb, top, bot;
            int t_in, b_in;
            uint32_t j;
#define LEVEL(idx, out)                                                                                                \
    do {                                                                                                               \
        float ff = k->rf[RI(k, (idx))];                                                                                \
        out = -1;                                                                                                      \
        if (ff > 0) {                                                                                                  \
            for (j = 0; j < nu && u[j] != ff; j++) {}                                                                  \
            out = j < nu ? (int32_t)lev[j] : -9;                                                                       \
        }                                                                                                              \
    } while (0)
            LEVEL(i, c0);
            if (c0 != (int32_t)dom) continue;
            if (i == 0) continue; /* run start (same[0] is False) or the sample before it left the ring */
            LEVEL(i - 1, cprev);
            LEVEL(i + 1, c1n);
            if (i + 2 < k->n) LEVEL(i + 2, c2);
            else c2 = -100;
            if (!(cprev == c0 && c1n == c0 && c2 == c1n)) continue;
            dt = (double)k->rt[RI(k, i + 1)] - (double)k->rt[RI(k, i)];
            if (!(dt <= 1.5 * period)) continue;
            xa = (tb_real)k->rx[RI(k, i)];
            xb = (tb_real)k->rx[RI(k, i + 1)];
            L = (double)fa / 60.0 * dt;
            gap = L - fabs((double)(xb - xa));
            if (!(gap > 0.02 * L + 0.1)) continue;
            top = (xa + xb + (tb_real)L) / 2;
            bot = (xa + xb - (tb_real)L) / 2;
            t_in = top < x1 - tol;
            b_in = bot > x0 + tol;
            if (b_in && !t_in && top > up) up = top;
            if (t_in && !b_in && bot < down) down = bot;
        }
        x0 = down;
        x1 = up;
    }
    return clf_predict_one(m, x1 - x0, x0 + x1, feed_in[dom] / time_in[dom]);
}

static void clf_label_push(clf_t *k, double T, int32_t raw)
{
    if (raw >= 0) k->held = raw;
    k->lab_t[k->lab_head] = T;
    k->lab[k->lab_head] = k->held;
    k->lab_head = (k->lab_head + 1) % 4u;
    if (k->lab_n < 4) k->lab_n++;
}

static void clf_classify_due(const tb_model *m, clf_t *k, double t_now, int final)
{
    double step = (double)PV(m, m->off[O_BODY] + 1);
    if (!k->have_t0) return;
    for (;;) {
        double T = k->t0 + (double)k->g_next * step;
        if (!final && !(T < t_now)) break;
        if (final && T > k->last_t + 1e-9) break;
        clf_label_push(k, T, clf_window(m, k, T));
        k->g_next++;
    }
}

static int clf_step(const tb_model *m, clf_t *k, const tb_sample *s)
{
    uint32_t at;
    if (!k->have_t0) {
        k->have_t0 = 1;
        k->t0 = s->t_s;
        k->period = (double)PV(m, 0);
    }
    if (k->n == k->cap) { /* drop the oldest */
        k->n--;
    }
    at = k->head;
    k->rt[at] = (float)(s->t_s - k->t0);
    k->rx[at] = (float)s->axis_mm;
    k->rf[at] = (!s->measuring && s->feed_mm_min > 0) ? (float)s->feed_mm_min : -1.0f;
    k->head = (k->head + 1) % k->cap;
    k->n++;
    k->last_t = s->t_s;
    /* grid points before this sample can be classified now (their window and next sample are in) */
    clf_classify_due(m, k, s->t_s, 0);
    return TB_OK;
}

int tb_classifier_label_at(const tb_model *clf, double t_s, int32_t *label)
{
    const clf_t *k;
    uint32_t i;
    int32_t out = -1;
    double best = -1e300;
    if (!clf || !clf->state || clf->kind != TB_KIND_CLASSIFIER || !label) return TB_E_STATE;
    k = (const clf_t *)((const state_t *)clf->state)->ks;
    if (k->have_t0 && t_s > tb_model_ready_s(clf) + horizon_s(clf)) return TB_E_NOTREADY;
    if (k->lab_n == 0) {
        *label = -1;
        return k->have_t0 ? TB_OK : TB_E_NOTREADY;
    }
    for (i = 0; i < k->lab_n; i++) {
        uint32_t at = (k->lab_head + 4u - 1u - i) % 4u;
        if (k->lab_t[at] <= t_s + 1e-9 && k->lab_t[at] > best) {
            best = k->lab_t[at];
            out = k->lab[at];
        }
    }
    if (best == -1e300) {
        uint32_t oldest = (k->lab_head + 4u - k->lab_n) % 4u;
        if (k->lab_n == 4) return TB_E_LATE;
        out = t_s < k->lab_t[oldest] ? -1 : k->lab[oldest];
    }
    *label = out;
    return TB_OK;
}

/* --------------------------------------------------------- dispatch */
static void kind_sample(tb_model *m, state_t *st, const motion_t *mo, const tb_real *dT)
{
    switch (m->kind) {
    case TB_KIND_GRU: gru_push(m, (gru_t *)st->ks, mo->t_s, dT); break;
    case TB_KIND_PHYSICS: phys_sample(m, (phys_t *)st->ks, mo, dT); break;
    case TB_KIND_AR: ar_sample(m, (ar_t *)st->ks, mo, 0); break;
    case TB_KIND_LUMPED: lump_sample(m, (lump_t *)st->ks, mo, dT); break;
    default: break;
    }
}

static void kind_finish(tb_model *m, state_t *st)
{
    switch (m->kind) {
    case TB_KIND_PHYSICS: phys_finish(m, (phys_t *)st->ks); break;
    case TB_KIND_AR: {
        ar_sample(m, (ar_t *)st->ks, 0, 1);
        break;
    }
    case TB_KIND_LUMPED: lump_finish(m, (lump_t *)st->ks); break;
    default: break;
    }
}

/* is sample s acceptable to model m? (changes nothing) */
static int check_sample(const tb_model *m, const tb_sample *s)
{
    const state_t *st;
    const common_t *c;
    uint32_t j;
    if (!m || !m->state) return TB_E_STATE;
    st = (const state_t *)m->state;
    if (st->finished) return TB_E_STATE;
    if (!s || !isfinite(s->t_s) || !isfinite(s->axis_mm) || !isfinite(s->feed_mm_min) || !isfinite(s->load_N) ||
        fabs(s->axis_mm) > TB_MAX_AXIS_MM || fabs(s->feed_mm_min) > TB_MAX_FEED_MM_MIN || fabs(s->load_N) > TB_MAX_LOAD_N)
        return TB_E_INPUT;
    if (m->kind == TB_KIND_CLASSIFIER) {
        const clf_t *k = (const clf_t *)st->ks;
        if (k->have_t0 && !(s->t_s > k->last_t)) return TB_E_INPUT;
        if (k->have_t0 && s->t_s - k->last_t > TB_MAX_GAP_S) return TB_E_SAMPLING;
        return TB_OK;
    }
    if (m->kind == TB_KIND_AR) /* a negative value to a fractional power (thermbench raises there too) */
        for (j = 0; j < m->dims[3]; j++) {
            tb_real code = PV(m, m->off[O_A] + 2 * j), power = PV(m, m->off[O_A] + 2 * j + 1);
            double v = code == 0 ? s->feed_mm_min : s->load_N;
            if (v < 0 && power != floor(power)) return TB_E_INPUT;
        }
    c = st->cm;
    if (m->max_channel > 0 && (!s->temps_C || s->n_temps < m->max_channel)) return TB_E_INPUT;
    if (m->kind == TB_KIND_LUMPED && lump_check_u(m, lump_u(m, s)) != TB_OK) return TB_E_INPUT;
    if (c->n_in > 0) {
        if (!(s->t_s > c->t_last)) return TB_E_INPUT;
        if (s->t_s - c->t_last > TB_MAX_GAP_S) return TB_E_SAMPLING;
        if (c->period_s > 0) { /* on the period's grid from the first sample (samples may be missing) */
            double k = floor((s->t_s - c->t_first) / c->period_s + 0.5);
            if (fabs(s->t_s - (c->t_first + k * c->period_s)) > 1e-3 * c->period_s) return TB_E_SAMPLING;
        }
    }
    for (j = 0; j < c->S; j++) {
        double v = s->temps_C[(uint32_t)PV(m, m->off[O_SENS] + j)];
        if (!isfinite(v) || v < TB_MIN_TEMP_C || v > TB_MAX_TEMP_C) return TB_E_INPUT;
    }
    return TB_OK;
}

int tb_model_step(tb_model *m, const tb_sample *s)
{
    state_t *st;
    common_t *c;
    uint32_t j;
    int rc = check_sample(m, s);
    if (rc != TB_OK) return rc;
    st = (state_t *)m->state;
    if (m->kind == TB_KIND_CLASSIFIER) return clf_step(m, (clf_t *)st->ks, s);
    c = st->cm;
    {
        tb_real raw[TB_MAX_SENSORS];
        for (j = 0; j < c->S; j++) raw[j] = (tb_real)s->temps_C[(uint32_t)PV(m, m->off[O_SENS] + j)];
        if (c->n_in == 0) c->t_first = s->t_s;
        c->t_last = s->t_s;
        if (!c->started) {
            motion_t *b = &c->buf[c->n_in];
            b->t_s = s->t_s;
            b->axis_mm = s->axis_mm;
            b->feed_mm_min = s->feed_mm_min;
            b->load_N = s->load_N;
            b->op_u = m->kind == TB_KIND_LUMPED ? lump_u(m, s) : 0.0;
            b->measuring = s->measuring;
            for (j = 0; j < c->S; j++) c->buf_T[c->n_in * c->S + j] = raw[j];
            c->n_in++;
            if (c->n_in == NBUF) flush_start(m, st);
            return TB_OK;
        }
        c->n_in++;
        for (j = 0; j < c->S; j++) raw[j] = chain_one(m, c, j, raw[j]);
        {
            motion_t mo;
            mo.t_s = s->t_s;
            mo.axis_mm = s->axis_mm;
            mo.feed_mm_min = s->feed_mm_min;
            mo.load_N = s->load_N;
            mo.op_u = m->kind == TB_KIND_LUMPED ? lump_u(m, s) : 0.0;
            mo.measuring = s->measuring;
            process_sample(m, st, &mo, raw);
        }
    }
    return TB_OK;
}

int tb_model_finish(tb_model *m)
{
    state_t *st;
    if (!m || !m->state) return TB_E_STATE;
    st = (state_t *)m->state;
    if (st->finished) return TB_OK;
    st->finished = 1;
    if (m->kind == TB_KIND_CLASSIFIER) {
        clf_classify_due(m, (clf_t *)st->ks, 0, 1);
        return TB_OK;
    }
    if (!st->cm->started && st->cm->n_in > 0) flush_start(m, st);
    kind_finish(m, st);
    return TB_OK;
}

double tb_model_ready_s(const tb_model *m)
{
    const state_t *st;
    if (!m || !m->state) return -1e300;
    st = (const state_t *)m->state;
    switch (m->kind) {
    case TB_KIND_CLASSIFIER: {
        const clf_t *k = (const clf_t *)st->ks;
        if (!k->have_t0) return -1e300;
        return k->t0 + (double)k->g_next * (double)PV(m, m->off[O_BODY] + 1) - 1e-6;
    }
    case TB_KIND_PHYSICS: {
        const phys_t *p = (const phys_t *)st->ks;
        return p->n_snap ? p->snap_t[p->snap_cur] : -1e300;
    }
    case TB_KIND_AR: {
        const ar_t *r = (const ar_t *)st->ks;
        return r->started ? r->g_t[r->g_cur] : -1e300;
    }
    case TB_KIND_LUMPED: { /* the newest grid state: every value up to it is final */
        const lump_t *L = (const lump_t *)st->ks;
        return L->started ? L->t0 + (double)L->k * LU_STEP(m) : -1e300;
    }
    default: {
        const common_t *c = st->cm;
        return c->h_n ? c->h_t[(c->h_head + NHIST - 1) % NHIST] : -1e300;
    }
    }
}

/* how far past tb_model_ready_s a query may lie (the state is held, in real time) */
static double horizon_s(const tb_model *m)
{
    switch (m->kind) {
    case TB_KIND_PHYSICS: return (double)PV(m, m->off[O_BODY] + P_MACRO) + TB_MAX_GAP_S;
    case TB_KIND_AR: return (double)PV(m, m->off[O_BODY] + 1) + TB_MAX_GAP_S;
    case TB_KIND_LUMPED: return LU_STEP(m) + TB_MAX_GAP_S;
    case TB_KIND_CLASSIFIER: return (double)PV(m, m->off[O_BODY] + 1) + TB_MAX_GAP_S;
    default: return TB_MAX_GAP_S;
    }
}

int tb_model_predict(const tb_model *m, double t_s, double axis_mm, double *thermal_um, double *total_um)
{
    const state_t *st;
    tb_real dT[TB_MAX_SENSORS], th = 0;
    double total;
    int rc = TB_OK;
    if (!m || !m->state) return TB_E_STATE;
    if (m->kind == TB_KIND_CLASSIFIER) return TB_E_STATE;
    if (!isfinite(t_s) || !isfinite(axis_mm)) return TB_E_ARG;
    if (t_s > tb_model_ready_s(m) + horizon_s(m)) return TB_E_NOTREADY; /* stalled or not stepped that far */
    st = (const state_t *)m->state;
    switch (m->kind) {
    case TB_KIND_PHYSICS: rc = phys_predict(m, (const phys_t *)st->ks, t_s, axis_mm, &th); break;
    case TB_KIND_AR: rc = ar_predict(m, (const ar_t *)st->ks, t_s, axis_mm, &th); break;
    case TB_KIND_GRU: rc = gru_predict(m, (const gru_t *)st->ks, t_s, axis_mm, &th); break;
    case TB_KIND_LUMPED: rc = lump_predict(m, (const lump_t *)st->ks, t_s, &th); break;
    default:
        rc = hist_at(st->cm, t_s, dT);
        if (rc != TB_OK) break;
        if (m->kind == TB_KIND_MLR_CURVE) th = mlr_curve_eval(m, dT, axis_mm);
        else if (m->kind == TB_KIND_MLR_SEED001) th = mlr001_eval(m, dT, axis_mm);
        else if (m->kind == TB_KIND_LSSVM) th = lssvm_eval(m, dT, axis_mm);
        else th = mlp_eval(m, dT, axis_mm);
    }
    if (rc != TB_OK) return rc;
    total = (double)th + tb_model_geometric_um(m, axis_mm);
    if (!isfinite(total)) return TB_E_INPUT; /* only hostile inputs get here */
    if (thermal_um) *thermal_um = (double)th;
    if (total_um) *total_um = total;
    return TB_OK;
}

/* ------------------------------------------------------------- bank */
int tb_bank_init(tb_bank *b, tb_model *classifier, tb_model *const *members, uint32_t n_members)
{
    uint32_t i;
    if (!b || !classifier || !members || classifier->kind != TB_KIND_CLASSIFIER || !classifier->state) return TB_E_STATE;
    if (n_members != classifier->dims[0] || n_members > TB_MAX_CONDITIONS) return TB_E_ARG;
    for (i = 0; i < n_members; i++)
        if (!members[i] || !members[i]->state || members[i]->kind == TB_KIND_CLASSIFIER) return TB_E_STATE;
    b->classifier = classifier;
    b->n_members = n_members;
    for (i = 0; i < n_members; i++) b->members[i] = members[i];
    return TB_OK;
}

int tb_bank_set_member(tb_bank *b, uint32_t i, tb_model *member)
{
    const clf_t *k;
    const common_t *c;
    if (!b || !b->classifier || i >= b->n_members) return TB_E_ARG;
    if (!member || !member->state || member->kind == TB_KIND_CLASSIFIER) return TB_E_STATE;
    /* a member must have seen the same samples as the bank (its dT baseline is the run's first
     * sample, a physics member integrates from the cold start): swap before the first sample,
     * or bring the new model up to date with the run's log first */
    k = (const clf_t *)((const state_t *)b->classifier->state)->ks;
    c = ((const state_t *)member->state)->cm;
    if (k->have_t0 != (c->n_in > 0)) return TB_E_STATE;
    if (k->have_t0 && (c->t_first != k->t0 || c->t_last != k->last_t)) return TB_E_STATE;
    b->members[i] = member;
    return TB_OK;
}

int tb_bank_step(tb_bank *b, const tb_sample *s)
{
    uint32_t i;
    int rc;
    if (!b || !b->classifier) return TB_E_STATE;
    rc = check_sample(b->classifier, s); /* all or nothing: a sample one model refuses changes none */
    for (i = 0; i < b->n_members && rc == TB_OK; i++) rc = check_sample(b->members[i], s);
    if (rc != TB_OK) return rc;
    rc = tb_model_step(b->classifier, s);
    if (rc != TB_OK) return rc;
    for (i = 0; i < b->n_members; i++) {
        rc = tb_model_step(b->members[i], s);
        if (rc != TB_OK) return rc;
    }
    return TB_OK;
}

int tb_bank_finish(tb_bank *b)
{
    uint32_t i;
    int rc;
    if (!b || !b->classifier) return TB_E_STATE;
    rc = tb_model_finish(b->classifier);
    for (i = 0; i < b->n_members && rc == TB_OK; i++) rc = tb_model_finish(b->members[i]);
    return rc;
}

double tb_bank_ready_s(const tb_bank *b)
{
    double r;
    uint32_t i;
    if (!b || !b->classifier) return -1e300;
    r = tb_model_ready_s(b->classifier);
    for (i = 0; i < b->n_members; i++) {
        double q = tb_model_ready_s(b->members[i]);
        if (q < r) r = q;
    }
    return r;
}

int tb_bank_predict(const tb_bank *b, double t_s, double axis_mm, double *thermal_um, double *total_um, int32_t *label)
{
    int32_t lab;
    uint32_t i;
    double geo = 0, total = 0;
    int rc;
    if (!b || !b->classifier) return TB_E_STATE;
    rc = tb_classifier_label_at(b->classifier, t_s, &lab);
    if (rc != TB_OK) return rc;
    for (i = 0; i < b->n_members; i++) geo += tb_model_geometric_um(b->members[i], axis_mm);
    geo /= (double)b->n_members;
    if (lab < 0 || (uint32_t)lab >= b->n_members) {
        lab = -1;
        total = geo; /* no condition yet: a cold axis, geometric error only */
    } else {
        rc = tb_model_predict(b->members[lab], t_s, axis_mm, 0, &total);
        if (rc != TB_OK) return rc;
    }
    if (thermal_um) *thermal_um = total - geo;
    if (total_um) *total_um = total;
    if (label) *label = lab;
    return TB_OK;
}
