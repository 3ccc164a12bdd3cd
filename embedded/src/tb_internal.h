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

#include <math.h>
#include <string.h>

/* ------------------------------------------------------------------ utils */
static inline uint32_t tbi_rd_u32(const uint8_t *p)
{
    return (uint32_t)p[0] | ((uint32_t)p[1] << 8) | ((uint32_t)p[2] << 16) | ((uint32_t)p[3] << 24);
}

static inline uint16_t tbi_rd_u16(const uint8_t *p) { return (uint16_t)(p[0] | (p[1] << 8)); }

static inline float tbi_rd_f32(const uint8_t *p)
{
    uint32_t u = tbi_rd_u32(p);
    float f;
    memcpy(&f, &u, sizeof f);
    return f;
}

/* payload value i of a model (float32 -> tb_real) */
#define PV(m, i) ((tb_real)tbi_rd_f32((m)->payload + 4u * (uint32_t)(i)))
/* a float32 (hi, lo) pair at i: hi + lo */
#define PR(m, i) (PV(m, i) + PV(m, (i) + 1u))

/* floor(v) as an integer clamped to [lo, hi] (NaN -> lo): no float-to-int overflow */
static inline int64_t tbi_floor_clamp(double v, int64_t lo, int64_t hi)
{
    if (!(v >= (double)lo)) return lo;
    if (v >= (double)hi) return hi;
    return (int64_t)floor(v);
}

/* numpy.interp between two samples, clamped */
static inline double tbi_interp1(double t, double t0, double t1, double v0, double v1)
{
    if (t <= t0 || t1 <= t0) return v0;
    if (t >= t1) return v1;
    return v0 + (t - t0) * ((v1 - v0) / (t1 - t0));
}

/* ceil(v - 1e-9) for v >= 0, at least 1, clamped to 2^40: the whole steps thermbench integrates */
static inline uint64_t tbi_steps_ceil(double v)
{
    uint64_t n = (uint64_t)-tbi_floor_clamp(-(v - 1e-9), -((int64_t)1 << 40), 0);
    return n < 1 ? 1 : n;
}

/* --------------------------------------------------------- parse cursor */
/* every read of a payload at open time goes through it: an out-of-range read sets err */
typedef struct {
    const tb_model *m;
    uint32_t pos;
    int err;
} tbi_cur;

uint32_t tbi_take(tbi_cur *c, uint32_t n);
uint32_t tbi_take_int(tbi_cur *c, uint32_t lo, uint32_t hi); /* an integer-valued entry in [lo, hi] */
tb_real tbi_take_val(tbi_cur *c, tb_real lo, tb_real hi, int strict_lo);
tb_real tbi_take_pair(tbi_cur *c, double lo, double hi, int strict_lo); /* a (hi, lo) pair: a double */
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
    double t_s, axis_mm, feed_mm_min, load_N;
    double op_u; /* the kind's operating input (tbi_kind.op_input; 0 without) */
    int measuring;
} tbi_motion;

typedef struct tbi_common tbi_common; /* the filters and the dT history (tb_runtime.c) */

typedef struct {
    tbi_common *cm; /* 0 for a kind without the sensor pipeline */
    void *ks;       /* kind state */
    int finished;   /* tb_model_finish was called: no more samples */
} tbi_state;

/* dT of every sensor at t, interpolated in the short history (numpy.interp over the log) */
int tbi_hist_at(const tbi_common *c, double t, tb_real *out);
/* is sample s acceptable to model m? (changes nothing; the bank checks every model first) */
int tbi_check_sample(const tb_model *m, const tb_sample *s);
/* the first and last sample accepted (0 before the first) */
int tbi_common_span(const tbi_common *c, double *t_first, double *t_last);

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
    double (*op_input)(const tb_model *m, const tb_sample *s);
    /* pipeline 0: one raw sample */
    int (*step)(const tb_model *m, void *ks, const tb_sample *s);
    /* pipeline 1: one processed sample, dT its sensors' rises; 0: nothing to do */
    void (*sample)(const tb_model *m, void *ks, const tbi_motion *mo, const tb_real *dT);
    void (*finish)(const tb_model *m, void *ks);            /* end of the log; 0: nothing */
    /* the time up to which its values are final (tb_model_ready_s) and, when horizon_s is not 0, how
     * far past it a query may lie (the state held); 0: the newest sample in the history, TB_MAX_GAP_S */
    double (*ready_s)(const tb_model *m, const void *ks, double *horizon_s);
    /* the thermal error: predict (a state of its own) or, when 0, eval on the dT history at t */
    int (*predict)(const tb_model *m, const void *ks, double t_s, double axis_mm, tb_real *thermal);
    tb_real (*eval)(const tb_model *m, const tb_real *dT, double axis_mm);
} tbi_kind;

/* the highest payload version of any kind (tbi_kind.max_version) */
#define TBI_MAX_VERSION 2u

static inline tb_real tbi_sigm(tb_real x) { return (tb_real)(1.0 / (1.0 + exp(-(double)x))); }

/* the kind table, indexed by TB_KIND_* (tb_registry.c); 0: no such kind (TB_E_KIND) */
extern const tbi_kind *const tbi_kinds[TB_KIND_MAX + 1];

static inline const tbi_kind *tbi_kind_of(uint32_t kind) { return kind <= TB_KIND_MAX ? tbi_kinds[kind] : 0; }

/* classifier internals the bank needs (tb_kind_classifier.c): 1 once stepped, with its span */
int tbi_classifier_span(const tb_model *clf, double *t_first, double *t_last);

#endif /* TB_INTERNAL_H */
