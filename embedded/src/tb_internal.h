/*
 * tb_internal.h - what the runtime's source files share (not part of the public API: users
 * include tb_runtime.h only).
 *
 * The runtime is a core (tb_runtime.c: file header and validation, the payload cursor, the
 * arena, the sensor pipeline, the geometric block, the public API) and one file per model
 * kind (tb_kind_<name>.c), each exporting a table of functions, tbi_kind, listed in
 * tb_registry.def. The physics kind has one file per effect (tb_fx_<name>.c, tb_physics.h),
 * listed there too. Every name with external linkage that is not public starts with tbi_.
 */
#ifndef TB_INTERNAL_H
#define TB_INTERNAL_H

#include "tb_runtime.h"

#include <float.h>
#include <math.h>
#include <string.h>

/* -DTB_SINGLE: float throughout (tb_runtime.h); a float tb_real without it would keep 64-bit counters */
#ifdef TB_SINGLE
typedef int32_t tbi_int;    /* a whole number of steps or samples computed from a time */
typedef uint32_t tbi_count; /* steps taken since the first sample */
#define TBI_COUNT_MAX 0x7FFFFFFFu
#else
typedef int64_t tbi_int;
typedef uint64_t tbi_count;
#define TBI_COUNT_MAX ((uint64_t)1 << 40)
#endif
typedef char tbi_single_is_float_[(sizeof(tb_real) == 4) == (sizeof(tbi_int) == 4) ? 1 : -1]; /* use -DTB_SINGLE */

/* a constant in the runtime's precision (a bare 1e-9 would make float arithmetic double) */
#define TB_R(x) ((tb_real)(x))

/* <math.h> in the runtime's precision: the float functions in TB_SINGLE */
#ifdef TB_SINGLE
#define tbm_exp tbi_expf /* below: newlib's expf (fdlibm's, behind an errno wrapper) takes about twice the instructions */
#define tbm_floor floorf
#define tbm_ceil ceilf
#define tbm_fabs fabsf
#define tbm_tanh tbi_tanhf /* below: one expf, as the sigmoid (newlib's tanhf costs several times more) */
#define tbm_pow powf
#define tbm_sin sinf
#define tbm_erf erff
#else
#define tbm_exp exp
#define tbm_floor floor
#define tbm_ceil ceil
#define tbm_fabs fabs
#define tbm_tanh tanh
#define tbm_pow pow
#define tbm_sin sin
#define tbm_erf erf
#endif

/* ------------------------------------------------------------------ utils */
/* little-endian reads of the model file; on a little-endian machine one load each (the file is on a
 * 4-byte boundary, tb_model_open checks it, so every value is read aligned) */
#if defined(__BYTE_ORDER__) && defined(__ORDER_LITTLE_ENDIAN__) && __BYTE_ORDER__ == __ORDER_LITTLE_ENDIAN__
static inline uint32_t tbi_rd_u32(const uint8_t *p)
{
    uint32_t u;
    memcpy(&u, p, sizeof u);
    return u;
}

static inline uint16_t tbi_rd_u16(const uint8_t *p)
{
    uint16_t u;
    memcpy(&u, p, sizeof u);
    return u;
}
#else
static inline uint32_t tbi_rd_u32(const uint8_t *p)
{
    return (uint32_t)p[0] | ((uint32_t)p[1] << 8) | ((uint32_t)p[2] << 16) | ((uint32_t)p[3] << 24);
}

static inline uint16_t tbi_rd_u16(const uint8_t *p) { return (uint16_t)(p[0] | (p[1] << 8)); }
#endif

static inline float tbi_rd_f32(const uint8_t *p)
{
    uint32_t u = tbi_rd_u32(p);
    float f;
    memcpy(&f, &u, sizeof f);
    return f;
}

/* float32 values of the payload read in place, as floats (gcc and clang: the type may alias the
 * file's bytes; the file is on a 4-byte boundary, checked at open): a dot product's weights load
 * straight into FPU registers. Elsewhere, or on a big-endian machine, through tbi_rd_f32. */
#if defined(__GNUC__) && defined(__BYTE_ORDER__) && defined(__ORDER_LITTLE_ENDIAN__) && \
    __BYTE_ORDER__ == __ORDER_LITTLE_ENDIAN__
typedef float __attribute__((__may_alias__)) tbi_f32;
#define TBI_W(w, j) ((tb_real)((const tbi_f32 *)(const void *)(w))[j])
#else
#define TBI_W(w, j) ((tb_real)tbi_rd_f32((w) + 4u * (uint32_t)(j)))
#endif

/* sum_j w[j] h[j] over n float32 weights w of the payload: four running sums, added at the end
 * ((s0 + s1) + (s2 + s3)), so the M4 overlaps their loads and multiplies */
static inline tb_real tbi_dot(const uint8_t *w, const tb_real *h, uint32_t n)
{
    tb_real s0 = 0, s1 = 0, s2 = 0, s3 = 0;
    uint32_t j = 0;
    for (; j + 4u <= n; j += 4u) {
        s0 += TBI_W(w, j) * h[j];
        s1 += TBI_W(w, j + 1u) * h[j + 1u];
        s2 += TBI_W(w, j + 2u) * h[j + 2u];
        s3 += TBI_W(w, j + 3u) * h[j + 3u];
    }
    for (; j < n; j++) s0 += TBI_W(w, j) * h[j];
    return (s0 + s1) + (s2 + s3);
}

/* payload value i of a model (float32 -> tb_real) */
#define PV(m, i) ((tb_real)tbi_rd_f32((m)->payload + 4u * (uint32_t)(i)))
/* a float32 (hi, lo) pair at i: hi + lo */
#define PR(m, i) (PV(m, i) + PV(m, (i) + 1u))

/* floor(v) as an integer clamped to [lo, hi] (NaN -> lo): no float-to-int overflow */
static inline tbi_int tbi_floor_clamp(tb_real v, tbi_int lo, tbi_int hi)
{
    if (!(v >= (tb_real)lo)) return lo;
    if (v >= (tb_real)hi) return hi;
    return (tbi_int)tbm_floor(v);
}

/* numpy.interp between two samples, clamped */
static inline tb_real tbi_interp1(tb_real t, tb_real t0, tb_real t1, tb_real v0, tb_real v1)
{
    if (t <= t0 || t1 <= t0) return v0;
    if (t >= t1) return v1;
    return v0 + (t - t0) * ((v1 - v0) / (t1 - t0));
}

/* ceil(v - 1e-9) for v >= 0, at least 1, clamped to TBI_COUNT_MAX: the whole steps thermbench integrates */
static inline tbi_count tbi_steps_ceil(tb_real v)
{
    tbi_count n = (tbi_count)-tbi_floor_clamp(-(v - TB_R(1e-9)), -(tbi_int)TBI_COUNT_MAX, 0);
    return n < 1 ? 1 : n;
}

/* --------------------------------------------------------- parse cursor */
/* every read of a payload at open time goes through it: an out-of-range read sets err */
typedef struct {
    const tb_model *m;
    uint32_t pos;
    int err;
} tbi_cur;

/* a data file's header (tb_model_open, tb_guard_open): alignment, size, magic, version range, CRC */
int tbi_check_file(const uint8_t *file, size_t len, uint16_t *version, uint16_t *kind, uint32_t *n_payload);
int tbi_check_dims(const uint8_t *file, uint32_t dims[TB_MAX_DIMS]); /* n_dims, flags, unused dims 0 */
int tbi_payload_finite(const uint8_t *payload, uint32_t n);          /* TB_E_NAN for a non-finite value */
/* tb_model_open after the file's header: a model of kind, layout version and dims whose payload is the n float32
 * values at payload (4-byte aligned); the ENSEMBLE kind opens its members with it */
int tbi_open_parts(tb_model *m, uint16_t kind, uint16_t version, const uint32_t dims[TB_MAX_DIMS], const uint8_t *payload,
                   uint32_t n_payload);
uint32_t tbi_take(tbi_cur *c, uint32_t n);
uint32_t tbi_take_int(tbi_cur *c, uint32_t lo, uint32_t hi); /* an integer-valued entry in [lo, hi] */
tb_real tbi_take_val(tbi_cur *c, tb_real lo, tb_real hi, int strict_lo);
tb_real tbi_take_pair(tbi_cur *c, tb_real lo, tb_real hi, int strict_lo); /* a (hi, lo) pair: hi + lo */
void tbi_parse_sensors(tbi_cur *c, tb_model *m, uint32_t S);      /* the sensor block of S sensors */
void tbi_parse_geom(tbi_cur *c, tb_model *m);                     /* the geometric block */

/* section offsets (tb_model.off, in float32 values) */
enum {
    O_PERIOD = 0, /* sample period, s (0: any) */
    O_SENS,       /* sensor block */
    O_GEOM,       /* geometric block */
    O_BODY,       /* kind-specific body */
    O_A, O_B, O_C, O_D, O_E, O_F, /* kind-specific sub-sections */
    O_COUNT
};

/* ---------------------------------------------------------------- arena */
typedef struct {
    uint8_t *p; /* 0 while sizing */
    size_t used, cap;
    int err;
} tbi_arena;

void *tbi_carve(tbi_arena *a, size_t bytes); /* 8-byte aligned; 0 while sizing or when full */

/* --------------------------------------------------- the sensor pipeline */
/* the samples after the startup buffer (tb_runtime.c) */
typedef struct {
    tb_real t_s, axis_mm, feed_mm_min, load_N;
    tb_real op_u; /* the kind's operating input (tbi_kind.op_input; 0 without) */
    int measuring;
    const tb_real *T0; /* each sensor's first value (the rises' reference), in the sensor block's order */
} tbi_motion;

typedef struct tbi_common tbi_common; /* the filters and the dT history (tb_runtime.c) */

typedef struct {
    tbi_common *cm; /* 0 for a kind without the sensor pipeline */
    void *ks;       /* kind state */
    int finished;   /* tb_model_finish was called: no more samples */
} tbi_state;

/* dT of every sensor at t, interpolated in the short history (numpy.interp over the log) */
int tbi_hist_at(const tbi_common *c, tb_real t, tb_real *out);
/* is sample s acceptable to model m? (changes nothing; the bank checks every model first) */
int tbi_check_sample(const tb_model *m, const tb_sample *s);
/* the first and last sample accepted (0 before the first) */
int tbi_common_span(const tbi_common *c, tb_real *t_first, tb_real *t_last);

/* THERMAL_LAG's and LINEAR_HISTORY's payload around their NW per-input columns (tb_kind_thermal_lag.c): the
 * blocks and the body's head (0 on an error), then the codes and weights after the columns */
int tbi_parse_lag_head(tbi_cur *c, tb_model *m, uint32_t *src, uint32_t *ch);
void tbi_parse_lag_weights(tbi_cur *c, tb_model *m, uint32_t NW, uint32_t src, uint32_t ch, int starts);

/* ------------------------------------------ a query ring of A(t), B(t) */
/* The last values of a kind whose error is A(t) + x B(t) at its samples (thermal_lag, linear_history):
 * a query between samples interpolates A and B linearly (numpy.interp over the log, as thermbench) */
#define TBI_AB_RING (TB_START_SAMPLES + 2u) /* as the core's dT history: queries near the newest sample */

typedef struct {
    tb_real t[TBI_AB_RING], a[TBI_AB_RING], b[TBI_AB_RING];
    uint32_t head, n;
} tbi_abring;

static inline void tbi_ab_push(tbi_abring *r, tb_real t, tb_real A, tb_real B)
{
    r->t[r->head] = t;
    r->a[r->head] = A;
    r->b[r->head] = B;
    r->head = (r->head + 1u) % TBI_AB_RING;
    if (r->n < TBI_AB_RING) r->n++;
}

/* A(t) + x B(t) (B only with position terms): the newest values past the newest sample, the oldest
 * before the first (numpy clamps), TB_E_LATE before what the ring still holds */
static inline int tbi_ab_at(const tbi_abring *r, tb_real t, tb_real axis_mm, int position, tb_real *thermal)
{
    uint32_t newest, oldest, a, b, i;
    tb_real A, B;
    if (r->n == 0) return TB_E_NOTREADY;
    newest = (r->head + TBI_AB_RING - 1u) % TBI_AB_RING;
    oldest = (r->head + TBI_AB_RING - r->n) % TBI_AB_RING;
    if (t >= r->t[newest]) {
        A = r->a[newest];
        B = r->b[newest];
    } else if (t < r->t[oldest]) {
        if (r->n == TBI_AB_RING) return TB_E_LATE;
        A = r->a[oldest];
        B = r->b[oldest];
    } else {
        A = r->a[oldest];
        B = r->b[oldest];
        b = newest;
        for (i = 1; i < r->n; i++) {
            a = (b + TBI_AB_RING - 1u) % TBI_AB_RING;
            if (r->t[a] <= t) {
                A = tbi_interp1(t, r->t[a], r->t[b], r->a[a], r->a[b]);
                B = tbi_interp1(t, r->t[a], r->t[b], r->b[a], r->b[b]);
                break;
            }
            b = a;
        }
    }
    *thermal = position ? A + axis_mm * B : A;
    return TB_OK;
}

/* ------------------------------------------------------- the kind table */
/* One model kind. The core calls these; 0 (NULL) entries take the default noted. */
typedef struct {
    uint16_t kind;        /* TB_KIND_* */
    uint16_t max_version; /* highest payload version it reads (the header's version) */
    int pipeline;         /* 1: samples go through the sensor pipeline (filters, dT history) and the
                           * file has the sensor and geometric blocks; 0: step() takes raw samples */
    /* check the dims and take the payload's sections after the period (the loader then
     * refuses a payload that is not used exactly) */
    void (*parse)(tbi_cur *c, tb_model *m, uint16_t version);
    /* place the kind's running state (*ks) in the arena (a->p == 0: sizing only); 0: none */
    void (*carve)(const tb_model *m, tbi_arena *a, void **ks);
    /* is sample s acceptable beyond the common checks? (channels are checked); 0: yes */
    int (*check)(const tb_model *m, const void *ks, const tb_sample *s);
    /* the operating input a sample carries for the kind (tbi_motion.op_u); 0: none */
    tb_real (*op_input)(const tb_model *m, const tb_sample *s);
    /* pipeline 0: one raw sample */
    int (*step)(const tb_model *m, void *ks, const tb_sample *s);
    /* pipeline 1: one processed sample, dT its sensors' rises; 0: nothing to do */
    void (*sample)(const tb_model *m, void *ks, const tbi_motion *mo, const tb_real *dT);
    void (*finish)(const tb_model *m, void *ks);            /* end of the log; 0: nothing */
    /* the time up to which its values are final (tb_model_ready_s) and, when horizon_s is not 0, how
     * far past it a query may lie (the state held); 0: the newest sample in the history, TB_MAX_GAP_S */
    tb_real (*ready_s)(const tb_model *m, const void *ks, tb_real *horizon_s);
    /* the thermal error: predict (a state of its own) or, when 0, eval on the dT history at t */
    int (*predict)(const tb_model *m, const void *ks, tb_real t_s, tb_real axis_mm, tb_real *thermal);
    tb_real (*eval)(const tb_model *m, const tb_real *dT, tb_real axis_mm);
} tbi_kind;

/* the highest payload version of any kind (tbi_kind.max_version) */
#define TBI_MAX_VERSION 2u

#ifdef TB_SINGLE
/* e^x in float for the kernels and activations: x = n ln2 + r (n = round(x / ln2), ln2 in two parts
 * as Cody and Waite, |r| <= ln2 / 2), e^r by its Taylor polynomial of degree 7 (remainder below
 * 3e-9 relative), 2^n put into the exponent field; below -87.3 the result (< FLT_MIN) is 0, above
 * 88.7 infinity, NaN stays NaN. Within 2 float32 ulps of e^x (tests/test_native.py), in a few dozen
 * instructions and no call. */
static inline float tbi_expf(float x)
{
    union { float f; uint32_t u; } s;
    float n, r, p;
    if (!(x < 88.72f)) return x != x ? x : HUGE_VALF;
    if (x < -87.33f) return 0.0f;
    n = (float)(int32_t)(x * 1.44269504f + (x >= 0.0f ? 0.5f : -0.5f));
    r = (x - n * 0.693145752f) - n * 1.42860677e-6f;
    p = 1.0f + r * (1.0f + r * (0.5f + r * (1.66666667e-1f + r * (4.16666667e-2f + r * (8.33333333e-3f +
        r * (1.38888889e-3f + r * 1.98412698e-4f)))))); /* fmt: the Taylor coefficients 1/k! */
    if (n > 127.0f) { /* x in [88.03, 88.72): 2^128 is beyond float's exponents, so 2^127 * 2 */
        s.u = 254u << 23;
        return p * s.f * 2.0f;
    }
    s.u = (uint32_t)((int32_t)n + 127) << 23;
    return p * s.f;
}
#endif

static inline tb_real tbi_sigm(tb_real x) { return 1 / (1 + tbm_exp(-x)); }

#ifdef TB_SINGLE
/* tanh x = 1 - 2 / (1 + e^(2x)): within a few float32 ulps of 1 absolute (what a network's
 * activations need), saturating cleanly (e^(2x) = inf gives 1, 0 gives -1) */
static inline float tbi_tanhf(float x) { return 1.0f - 2.0f / (1.0f + tbi_expf(2.0f * x)); }
#endif

/* "no time yet" (tb_model_ready_s before the first samples) */
#define TBI_NO_TIME TB_R(-1e30)

/* the latest time strictly before t, in the build's precision: "ready for every t' < t". A fixed
 * margin (t - 1e-6) vanishes in single precision past a few seconds (at 840 s the spacing of floats
 * is 6.1e-5) and then says ready at t itself */
#ifdef TB_SINGLE
#define TBI_BEFORE(t) nextafterf((t), -HUGE_VALF)
#else
#define TBI_BEFORE(t) nextafter((t), -HUGE_VAL)
#endif

/* how far apart two times of magnitude about |t| may be by rounding alone in the build's precision
 * (a few units in the last place): a time on a grid, computed as t_first + k * period, is "on it" to
 * this much more than the grid's own tolerance (floats are 1/64 s apart at 1.5 days, 0.5 s at 2^22 s) */
#ifdef TB_SINGLE
#define TBI_TIME_SLACK(t) (TB_R(4) * FLT_EPSILON * tbm_fabs(t))
#else
#define TBI_TIME_SLACK(t) (TB_R(4) * DBL_EPSILON * tbm_fabs(t))
#endif

/* the kind table, indexed by TB_KIND_* (tb_registry.c); 0: no such kind (TB_E_KIND) */
extern const tbi_kind *const tbi_kinds[TB_KIND_MAX + 1];

static inline const tbi_kind *tbi_kind_of(uint32_t kind) { return kind <= TB_KIND_MAX ? tbi_kinds[kind] : 0; }

/* classifier internals the bank needs (tb_kind_classifier.c): 1 once stepped, with its span */
int tbi_classifier_span(const tb_model *clf, tb_real *t_first, tb_real *t_last);

#endif /* TB_INTERNAL_H */
