/*
 * tb_runtime.c - thermbench embedded compensator runtime (see tb_runtime.h): the core.
 *
 * C99, no heap, only <math.h> and <string.h>. Every read of a model file goes
 * through a bounds-checked cursor at open time; after a successful open the
 * layout is known to fit the payload, so evaluation indexes it directly.
 *
 * This file: the file header and its checks, the payload cursor, the sensor block and its
 * filters (seed 002 §2.3.1 eq. 1-3: limit filter, scalar Kalman) with the dT history, the
 * geometric block, the arena and the public API, which hands each call to the model kind's
 * table (tbi_kind, tb_internal.h). The kinds, each in its own file (tb_registry.def):
 *   MLR curve    seed 002 eq. 6-11, seed 004 (curve coefficients linear in dT)
 *   MLR seed001  seed 001 eq. 12
 *   LSSVM        seed 002 eq. 12-14 (RBF kernel exp(-d^2 / (2 sigma^2)))
 *   MLP, GRU
 *   physics      seed 000 §3.1-3.2 finite differences, §4.1 heat model, §4.3 compensation
 *                table (full-length error array, interpolated), the effects one file each
 *   AR           seed 003 (our reading: ARX of curve coefficients on feed)
 *   classifier   seed 002 §2.4 eq. 15-19 (proximity naive Bayes); the bank in tb_bank.c
 *   lumped       docs/concepts.md "A lumped thermal network for a spindle" (physics_spindle)
 */
#include "tb_internal.h"

typedef char off_fits_[(sizeof(((tb_model *)0)->off) / sizeof(uint32_t) >= O_COUNT) ? 1 : -1];

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
    case TB_E_ALIGN: return "model file not 4-byte aligned";
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

/* --------------------------------------------------------- parse cursor */
uint32_t tbi_take(tbi_cur *c, uint32_t n)
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
uint32_t tbi_take_int(tbi_cur *c, uint32_t lo, uint32_t hi)
{
    uint32_t at = tbi_take(c, 1);
    tb_real v;
    if (c->err) return 0;
    v = PV(c->m, at);
    if (!(v >= (tb_real)lo && v <= (tb_real)hi) || v != tbm_floor(v)) {
        c->err = TB_E_PAYLOAD;
        return 0;
    }
    return (uint32_t)v;
}

/* a float32 (hi, lo) pair: a double-precision value (hi + lo, rounded to tb_real) in [lo, hi] ((lo, hi] if strict_lo) */
tb_real tbi_take_pair(tbi_cur *c, tb_real lo, tb_real hi, int strict_lo)
{
    uint32_t at = tbi_take(c, 2);
    tb_real v;
    if (c->err) return 0;
    v = PR(c->m, at);
    if ((strict_lo ? !(v > lo) : !(v >= lo)) || !(v <= hi)) {
        c->err = TB_E_PAYLOAD;
        return 0;
    }
    return v;
}

tb_real tbi_take_val(tbi_cur *c, tb_real lo, tb_real hi, int strict_lo)
{
    uint32_t at = tbi_take(c, 1);
    tb_real v;
    if (c->err) return 0;
    v = PV(c->m, at);
    if ((strict_lo ? !(v > lo) : !(v >= lo)) || !(v <= hi)) {
        c->err = TB_E_PAYLOAD;
        return 0;
    }
    return v;
}

#define FSTEP_VALS 5u /* type, p1 (hi, lo), p2 (hi, lo): float32 pairs keep the double thresholds */
#define SENS_PER (1u + FSTEP_VALS * TB_MAX_FILTER_STEPS)

/* sensor block: S channel indices, then per sensor [n_steps, (type, p1, p2) x 4] */
void tbi_parse_sensors(tbi_cur *c, tb_model *m, uint32_t S)
{
    uint32_t j, k, at;
    m->off[O_SENS] = c->pos;
    m->n_sensors = S;
    m->max_channel = 0;
    for (j = 0; j < S; j++) {
        uint32_t ch = tbi_take_int(c, 0, TB_MAX_SENSORS * 4u);
        if (ch + 1u > m->max_channel) m->max_channel = ch + 1u;
    }
    for (j = 0; j < S && !c->err; j++) {
        uint32_t n = tbi_take_int(c, 0, TB_MAX_FILTER_STEPS);
        at = tbi_take(c, FSTEP_VALS * TB_MAX_FILTER_STEPS);
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
                if (!(p1 > 0) || !(p2 >= 0) || p2 != tbm_floor(p2) || p2 > TB_R(1e9)) c->err = TB_E_PAYLOAD;
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
void tbi_parse_geom(tbi_cur *c, tb_model *m)
{
    uint32_t gtype, n, at, i, extra;
    m->off[O_GEOM] = c->pos;
    gtype = tbi_take_int(c, 0, 2);
    n = tbi_take_int(c, 0, TB_MAX_TABLE);
    tbi_take(c, 2);
    if (c->err) return;
    if (gtype == 0 && n != 0) c->err = TB_E_PAYLOAD;
    if (gtype == 1 && (n < 1 || n > TB_MAX_POLY)) c->err = TB_E_DIMS;
    if (gtype == 2 && n < 1) c->err = TB_E_DIMS;
    if (c->err) return;
    at = tbi_take(c, gtype == 2 ? 2u * n : n);
    if (c->err) return;
    if (gtype == 2)
        for (i = 1; i < n; i++)
            if (!(PV(m, at + i) > PV(m, at + i - 1))) c->err = TB_E_PAYLOAD;
    extra = tbi_take_int(c, 0, TB_MAX_POLY);
    tbi_take(c, 1 + extra);
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

/* the geometric block at axis_mm (a model with the block) */
static inline tb_real geometric_um(const tb_model *m, tb_real axis_mm)
{
    uint32_t g, gtype, n, extra, base;
    tb_real out = 0, x = axis_mm;
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
            out = tbi_interp1(x, PV(m, base + lo), PV(m, base + hi), PV(m, base + n + lo),
                                   PV(m, base + n + hi));
        }
    }
    base += gtype == 2 ? 2 * n : (gtype == 1 ? n : 0);
    extra = (uint32_t)PV(m, base);
    if (extra) out += poly_eval(m, base + 2, extra, x - PV(m, base + 1));
    return out;
}

tb_real tb_model_geometric_um(const tb_model *m, tb_real axis_mm)
{
    if (!m || !m->payload || !m->off[O_GEOM]) return 0; /* no geometric block (the classifier) */
    return geometric_um(m, axis_mm);
}

/* ---------------------------------------------------------------- arena */
void *tbi_carve(tbi_arena *a, size_t bytes)
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

struct tbi_common {
    uint32_t S, n_steps; /* channels; filter steps allocated per channel */
    uint32_t n_in;      /* samples received */
    uint32_t started;   /* startup buffer flushed */
    tb_real period_s;
    tb_real t_first, t_last; /* first and last accepted sample */
    tbi_motion buf[NBUF];
    tb_real *buf_T;     /* NBUF x S raw temperatures */
    fstate_t *fs;       /* S x TB_MAX_FILTER_STEPS */
    tb_real *T0;        /* first filtered value per channel */
    /* history of processed samples */
    uint32_t h_n, h_head;
    tb_real h_t[NHIST];
    tb_real *h_dT;      /* NHIST x S */
};

static uint32_t max_steps(const tb_model *m)
{
    uint32_t j, mx = 0;
    for (j = 0; j < m->n_sensors; j++) {
        uint32_t n = (uint32_t)PV(m, m->off[O_SENS] + m->n_sensors + SENS_PER * j);
        if (n > mx) mx = n;
    }
    return mx ? mx : 1;
}

static void common_carve(const tb_model *m, tbi_arena *a, tbi_common **cm, uint32_t S)
{
    uint32_t ns = max_steps(m);
    tbi_common *c = (tbi_common *)tbi_carve(a, sizeof(tbi_common));
    tb_real *bt = (tb_real *)tbi_carve(a, sizeof(tb_real) * NBUF * (S ? S : 1));
    fstate_t *fs = (fstate_t *)tbi_carve(a, sizeof(fstate_t) * ns * (S ? S : 1));
    tb_real *t0 = (tb_real *)tbi_carve(a, sizeof(tb_real) * (S ? S : 1));
    tb_real *hd = (tb_real *)tbi_carve(a, sizeof(tb_real) * NHIST * (S ? S : 1));
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
        if (tbm_fabs(z - f->prev) <= p1) {
            f->prev = z;
            f->run = 0;
            return z;
        }
        if (max_hold > 0) {
            f->run = (f->run && tbm_fabs(z - f->last_rej) <= p1) ? f->run + 1 : 1;
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
static void chain_batch(const tb_model *m, tbi_common *c, uint32_t j, tb_real *v, uint32_t n)
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
            tb_real limit = PV(m, at + 1) + PV(m, at + 2);
            if (tbm_fabs(v[0] - med) > limit && hi - lo <= limit)
                v[0] = med;
        }
        for (i = 0; i < n; i++) v[i] = fstep_apply(m, at, f, v[i]);
    }
}

static tb_real chain_one(const tb_model *m, tbi_common *c, uint32_t j, tb_real z)
{
    uint32_t s_at = m->off[O_SENS] + c->S + SENS_PER * j;
    uint32_t k, nsteps = (uint32_t)PV(m, s_at);
    for (k = 0; k < nsteps; k++)
        z = fstep_apply(m, s_at + 1 + FSTEP_VALS * k, &c->fs[j * c->n_steps + k], z);
    return z;
}

/* dT of channel j at history slot h */
#define HDT(c, h, j) ((c)->h_dT[(h) * (c)->S + (j)])

static void hist_push(tbi_common *c, tb_real t, const tb_real *dT)
{
    uint32_t j, h = c->h_head;
    c->h_t[h] = t;
    for (j = 0; j < c->S; j++) HDT(c, h, j) = dT[j];
    c->h_head = (h + 1) % NHIST;
    if (c->h_n < NHIST) c->h_n++;
}

/* dT of every channel at t, interpolated in the history (numpy.interp over the log) */
int tbi_hist_at(const tbi_common *c, tb_real t, tb_real *out)
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
                out[j] = tbi_interp1(t, c->h_t[a], c->h_t[b], HDT(c, a, j), HDT(c, b, j));
            return TB_OK;
        }
        b = a;
    }
    for (j = 0; j < c->S; j++) out[j] = HDT(c, oldest, j);
    return TB_OK;
}

int tbi_common_span(const tbi_common *c, tb_real *t_first, tb_real *t_last)
{
    *t_first = c->t_first;
    *t_last = c->t_last;
    return c->n_in > 0;
}

/* ------------------------------------------------------ kind interface */
static void process_sample(const tbi_kind *ops, tb_model *m, tbi_state *st, const tbi_motion *mo, tb_real *filtered)
{
    tbi_common *c = st->cm;
    tb_real dT[TB_MAX_SENSORS];
    uint32_t j;
    if (c->h_n == 0 && c->n_in >= 1) {
        for (j = 0; j < c->S; j++) c->T0[j] = filtered[j];
    }
    for (j = 0; j < c->S; j++) dT[j] = filtered[j] - c->T0[j];
    hist_push(c, mo->t_s, dT);
    if (ops->sample) {
        tbi_motion with = *mo;
        with.T0 = c->T0;
        ops->sample(m, st->ks, &with, dT);
    }
}

static void flush_start(const tbi_kind *ops, tb_model *m, tbi_state *st)
{
    tbi_common *c = st->cm;
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
        process_sample(ops, m, st, &c->buf[i], filt);
    }
}

/* ------------------------------------------------------------- open */
int tbi_check_file(const uint8_t *file, size_t len, uint16_t *version, uint16_t *kind, uint32_t *n_payload)
{
    uint32_t crc;
    /* the file is read in place with 16- and 32-bit loads at their natural offsets (a compiler may
       merge the byte reads into them): a file on a 4-byte boundary is never read unaligned */
    if (((uintptr_t)file & 3u) != 0u) return TB_E_ALIGN;
    if (len < TB_HEADER_BYTES + 4u) return TB_E_SIZE;
    if (memcmp(file, TB_MAGIC, 4) != 0) return TB_E_MAGIC;
    *version = tbi_rd_u16(file + 4);
    if (*version < TB_FORMAT_VERSION || *version > TBI_MAX_VERSION) return TB_E_VERSION;
    *kind = tbi_rd_u16(file + 6);
    *n_payload = tbi_rd_u32(file + 44);
    if (*n_payload > TB_MAX_PAYLOAD) return TB_E_DIMS;
    if ((size_t)*n_payload * 4u + TB_HEADER_BYTES + 4u != len) return TB_E_SIZE;
    tb_crc32_check(file, len - 4u, &crc);
    if (crc != tbi_rd_u32(file + len - 4u)) return TB_E_CRC;
    return TB_OK;
}

int tbi_check_dims(const uint8_t *file, uint32_t dims[TB_MAX_DIMS])
{
    uint32_t i, n_dims = tbi_rd_u16(file + 8);
    if (n_dims > TB_MAX_DIMS || tbi_rd_u16(file + 10) != 0) return TB_E_DIMS;
    for (i = 0; i < TB_MAX_DIMS; i++) {
        dims[i] = tbi_rd_u32(file + 12 + 4 * i);
        if (i >= n_dims && dims[i] != 0) return TB_E_DIMS;
    }
    return TB_OK;
}

int tbi_payload_finite(const uint8_t *payload, uint32_t n)
{
    uint32_t i;
    for (i = 0; i < n; i++)
        if (!isfinite(tbi_rd_f32(payload + 4u * i))) return TB_E_NAN;
    return TB_OK;
}

int tb_model_open(tb_model *m, const uint8_t *file, size_t len)
{
    uint32_t n_payload;
    uint16_t version, kind;
    const tbi_kind *ops;
    int rc;
    if (!m) return TB_E_ARG;
    memset(m, 0, sizeof *m);
    if (!file) return TB_E_ARG;
    if ((rc = tbi_check_file(file, len, &version, &kind, &n_payload)) != TB_OK) return rc;
    ops = tbi_kind_of(kind);
    if (!ops || ops->kind != kind) return TB_E_KIND;
    if (version > ops->max_version) return TB_E_VERSION; /* a payload version this kind does not have */
    if ((rc = tbi_check_dims(file, m->dims)) != TB_OK) return rc;
    return tbi_open_parts(m, kind, version, m->dims, file + TB_HEADER_BYTES, n_payload);
}

int tbi_open_parts(tb_model *m, uint16_t kind, uint16_t version, const uint32_t dims[TB_MAX_DIMS], const uint8_t *payload,
                   uint32_t n_payload)
{
    const tbi_kind *ops;
    tbi_cur c;
    int rc;
    uint32_t d[TB_MAX_DIMS];
    memcpy(d, dims, sizeof d); /* dims may be m->dims itself */
    memset(m, 0, sizeof *m);
    ops = tbi_kind_of(kind);
    if (!ops || ops->kind != kind) return TB_E_KIND;
    if (version < TB_FORMAT_VERSION || version > ops->max_version) return TB_E_VERSION; /* a layout this kind does not have */
    memcpy(m->dims, d, sizeof d);
    m->payload = payload;
    m->n_payload = n_payload;
    m->kind = kind;
    if ((rc = tbi_payload_finite(m->payload, n_payload)) != TB_OK) {
        memset(m, 0, sizeof *m);
        return rc;
    }
    c.m = m;
    c.pos = 0;
    c.err = 0;
    m->off[O_PERIOD] = tbi_take(&c, 1);
    if (!c.err && !(PV(m, 0) >= 0 && PV(m, 0) <= 3600)) c.err = TB_E_PAYLOAD;
    ops->parse(&c, m, version);
    if (!c.err && c.pos != n_payload) c.err = TB_E_DIMS;
    if (c.err) {
        int e = c.err;
        memset(m, 0, sizeof *m);
        return e;
    }
    return TB_OK;
}

/* ------------------------------------------------------------ state */
static size_t layout(const tb_model *m, void *arena, size_t bytes, tbi_state **st_out)
{
    const tbi_kind *ops = tbi_kinds[m->kind];
    tbi_arena a;
    tbi_state *st;
    tbi_common *cm = 0;
    void *ks = 0;
    a.p = (uint8_t *)arena;
    a.used = 0;
    a.cap = arena ? bytes : (size_t)-1;
    a.err = 0;
    st = (tbi_state *)tbi_carve(&a, sizeof(tbi_state));
    if (ops->pipeline) {
        common_carve(m, &a, &cm, m->n_sensors);
        if (arena && !a.err) cm->period_s = PV(m, 0);
    }
    if (ops->carve) ops->carve(m, &a, &ks);
    if (a.err) return 0;
    if (arena) {
        st->cm = cm;
        st->ks = ks;
    }
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
    tbi_state *st = 0;
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

/* ------------------------------------------------------------ samples */
/* is sample s acceptable to model m (of kind ops, started)? (changes nothing) */
static int check_sample(const tbi_kind *ops, const tb_model *m, const tb_sample *s)
{
    const tbi_state *st = (const tbi_state *)m->state;
    const tbi_common *c;
    uint32_t j;
    int rc;
    if (st->finished) return TB_E_STATE;
    if (!s || !isfinite(s->t_s) || !isfinite(s->axis_mm) || !isfinite(s->feed_mm_min) || !isfinite(s->load_N) ||
        tbm_fabs(s->axis_mm) > TB_MAX_AXIS_MM || tbm_fabs(s->feed_mm_min) > TB_MAX_FEED_MM_MIN || tbm_fabs(s->load_N) > TB_MAX_LOAD_N)
        return TB_E_INPUT;
    if (m->max_channel > 0 && (!s->temps_C || s->n_temps < m->max_channel)) return TB_E_INPUT;
    if (ops->check && (rc = ops->check(m, st->ks, s)) != TB_OK) return rc;
    if (!ops->pipeline) return TB_OK;
    c = st->cm;
    if (c->n_in > 0) {
        if (!(s->t_s > c->t_last)) return TB_E_INPUT;
        if (s->t_s - c->t_last > TB_MAX_GAP_S) return TB_E_SAMPLING;
        if (c->period_s > 0) { /* on the period's grid from the first sample (samples may be missing) */
            /* to 1e-3 of the period, plus the rounding of the times in this precision and that of the
             * period, a float32 in the file (0.1 s is 1.5e-9 s off: 1e-4 s after 3 hours of samples) */
            tb_real since = s->t_s - c->t_first;
            tb_real k = tbm_floor(since / c->period_s + TB_R(0.5));
            tb_real tol = TB_R(1e-3) * c->period_s + TBI_TIME_SLACK(s->t_s) + TB_R(FLT_EPSILON) * since;
            if (tbm_fabs(s->t_s - (c->t_first + k * c->period_s)) > tol) return TB_E_SAMPLING;
        }
    }
    for (j = 0; j < c->S; j++) {
        tb_real v = s->temps_C[(uint32_t)PV(m, m->off[O_SENS] + j)];
        if (!isfinite(v) || v < TB_MIN_TEMP_C || v > TB_MAX_TEMP_C) return TB_E_INPUT;
    }
    return TB_OK;
}

int tbi_check_sample(const tb_model *m, const tb_sample *s)
{
    const tbi_kind *ops = m && m->state ? tbi_kind_of(m->kind) : 0;
    return ops ? check_sample(ops, m, s) : TB_E_STATE;
}

int tb_model_step(tb_model *m, const tb_sample *s)
{
    const tbi_kind *ops;
    tbi_state *st;
    tbi_common *c;
    tbi_motion mo;
    tb_real raw[TB_MAX_SENSORS];
    uint32_t j;
    int rc;
    ops = m && m->state ? tbi_kind_of(m->kind) : 0;
    if (!ops) return TB_E_STATE;
    rc = check_sample(ops, m, s);
    if (rc != TB_OK) return rc;
    st = (tbi_state *)m->state;
    if (!ops->pipeline) return ops->step(m, st->ks, s);
    c = st->cm;
    for (j = 0; j < c->S; j++) raw[j] = s->temps_C[(uint32_t)PV(m, m->off[O_SENS] + j)];
    if (c->n_in == 0) c->t_first = s->t_s;
    c->t_last = s->t_s;
    mo.t_s = s->t_s;
    mo.axis_mm = s->axis_mm;
    mo.feed_mm_min = s->feed_mm_min;
    mo.load_N = s->load_N;
    mo.op_u = ops->op_input ? ops->op_input(m, s) : 0;
    mo.measuring = s->measuring;
    if (!c->started) {
        c->buf[c->n_in] = mo;
        for (j = 0; j < c->S; j++) c->buf_T[c->n_in * c->S + j] = raw[j];
        c->n_in++;
        if (c->n_in == NBUF) flush_start(ops, m, st);
        return TB_OK;
    }
    c->n_in++;
    for (j = 0; j < c->S; j++) raw[j] = chain_one(m, c, j, raw[j]);
    process_sample(ops, m, st, &mo, raw);
    return TB_OK;
}

int tb_model_finish(tb_model *m)
{
    const tbi_kind *ops;
    tbi_state *st;
    ops = m && m->state ? tbi_kind_of(m->kind) : 0;
    if (!ops) return TB_E_STATE;
    st = (tbi_state *)m->state;
    if (st->finished) return TB_OK;
    st->finished = 1;
    if (ops->pipeline && !st->cm->started && st->cm->n_in > 0) flush_start(ops, m, st);
    if (ops->finish) ops->finish(m, st->ks);
    return TB_OK;
}

/* ------------------------------------------------------------ queries */
/* tb_model_ready_s, and how far past it a query may lie (the state is held, in real time) */
static tb_real ready_s(const tbi_kind *ops, const tb_model *m, tb_real *horizon_s)
{
    const tbi_state *st = (const tbi_state *)m->state;
    const tbi_common *c;
    if (ops->ready_s) return ops->ready_s(m, st->ks, horizon_s);
    if (horizon_s) *horizon_s = TB_MAX_GAP_S;
    c = st->cm;
    return c->h_n ? c->h_t[(c->h_head + NHIST - 1) % NHIST] : TBI_NO_TIME;
}

tb_real tb_model_ready_s(const tb_model *m)
{
    const tbi_kind *ops = m && m->state ? tbi_kind_of(m->kind) : 0;
    return ops ? ready_s(ops, m, 0) : TBI_NO_TIME;
}

int tb_model_predict(const tb_model *m, tb_real t_s, tb_real axis_mm, tb_real *thermal_um, tb_real *total_um)
{
    const tbi_kind *ops;
    const tbi_state *st;
    tb_real th = 0;
    tb_real total, horizon = 0;
    int rc;
    ops = m && m->state ? tbi_kind_of(m->kind) : 0;
    if (!ops || (!ops->predict && !ops->eval)) return TB_E_STATE; /* the classifier: tb_classifier_label_at */
    if (!isfinite(t_s) || !isfinite(axis_mm)) return TB_E_ARG;
    if (t_s > ready_s(ops, m, &horizon) + horizon) return TB_E_NOTREADY; /* stalled or not stepped that far */
    st = (const tbi_state *)m->state;
    if (ops->predict) {
        rc = ops->predict(m, st->ks, t_s, axis_mm, &th);
    } else {
        tb_real dT[TB_MAX_SENSORS];
        rc = tbi_hist_at(st->cm, t_s, dT);
        if (rc == TB_OK) th = ops->eval(m, dT, axis_mm);
    }
    if (rc != TB_OK) return rc;
    total = th + geometric_um(m, axis_mm);
    if (!isfinite(total)) return TB_E_INPUT; /* only hostile inputs get here */
    if (thermal_um) *thermal_um = th;
    if (total_um) *total_um = total;
    return TB_OK;
}
