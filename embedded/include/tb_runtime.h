/*
 * tb_runtime.h - thermbench embedded thermal-error compensator runtime.
 *
 * Plain C99, no heap, nothing beyond <math.h>/<string.h>/<stdint.h>/<stddef.h>.
 * Models arrive as data files at run time (the data-only analogue of seed 002
 * §2.5 "dynamic loading": new models without reflashing, and no code is ever
 * executed from a file). A file is parsed in place: its float32 payload stays
 * where it is (flash or a caller buffer) and only the model's running state is
 * placed in a caller-supplied arena, sized by tb_model_arena_bytes().
 *
 * File format (little-endian; written by thermbench.export.fileformat):
 *   0  char[4] magic "TBMF"        4  u16 version          6  u16 kind
 *   8  u16 n_dims (<= 8)           10 u16 flags (0)       12 u32 dims[8]
 *   44 u32 n_payload               48 float32 payload[n_payload]
 *   48 + 4 n_payload   u32 CRC-32 (IEEE 802.3, as zlib.crc32) of all bytes before it
 * The version is that of the kind's payload layout: 1 for every kind, 2 for TB_KIND_PHYSICS
 * (its effects as sections); the runtime reads both physics layouts and refuses a version a
 * kind does not have (TB_E_VERSION).
 *
 * Sources: src/tb_runtime.c (the core) and one file per model kind and per physics effect,
 * all listed in src/tb_registry.def: compile every .c file of src/.
 *
 * Use:
 *   tb_model m; tb_model_open(&m, buf, len);                 validate + parse
 *   static uint8_t arena[...]; tb_model_start(&m, arena, sizeof arena);
 *   per control cycle (one process-log sample): tb_model_step(&m, &sample);
 *   tb_model_predict(&m, t_s, axis_mm, &thermal_um, &total_um);  compensation = -total
 *
 * Timing rule (what makes the C reproduce the Python models exactly): a value at
 * time t is final once the runtime has been stepped to a sample at or after t
 * (tb_model_ready_s() >= t). Between samples, inputs are linear in time, as
 * numpy.interp over the process log; the physics model answers from the
 * thermal-error table of its last two macro steps (seed 000 §4.3), the
 * auto-regressive model from its last two grid steps, the lumped network from
 * its last grid states (docs/concepts.md, physics_spindle).
 *
 * All numbers carry their unit in the name (_s, _mm, _um, _C, _mm_min, _N).
 */
#ifndef TB_RUNTIME_H
#define TB_RUNTIME_H

#include <stddef.h>
#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

/* The precision of every number the runtime computes with and of its API (times, positions,
 * temperatures, errors): double by default; -DTB_SINGLE for a single-precision FPU (Cortex-M4F),
 * where the runtime then does no double and no 64-bit arithmetic at all. In single precision,
 * times are float seconds: give them from a recent epoch (float holds whole and half seconds
 * exactly up to 2^22 s, 48 days, and its step is 2^-7 s at 1.5 days) - thermbench's logs start
 * at t = 0. */
#ifdef TB_SINGLE
#define TB_REAL float
#endif
#ifndef TB_REAL
#define TB_REAL double
#endif
typedef TB_REAL tb_real;

#define TB_MAGIC "TBMF"
#define TB_FORMAT_VERSION 1u /* the first version: every kind has it */
#define TB_HEADER_BYTES 48u
#define TB_MAX_DIMS 8u

/* hard limits: a file beyond them is "absurd" (TB_E_DIMS), never an overflow */
#define TB_MAX_SENSORS 32u
#define TB_MAX_FILTER_STEPS 4u
#define TB_MAX_PAYLOAD 4194304u /* float32 values (16 MB) */
#define TB_MAX_POLY 16u
#define TB_MAX_TABLE 4096u
#define TB_MAX_SUPPORT 65536u
#define TB_MAX_LAYERS 8u
#define TB_MAX_WIDTH 256u
#define TB_MAX_GRU_HIDDEN 128u
#define TB_MAX_LAGS 4096u
#define TB_MAX_NODES 4096u
#define TB_MAX_AR_ORDER 64u
#define TB_MAX_LUMPED_NODES 8u   /* nodes of a lumped network's chain (thermbench fits 1..6) */
#define TB_MAX_LAG_TAUS 8u       /* time constants of a thermal-lag model, delays of a linear-history one */
#define TB_MAX_DELAY_LINE 4096u  /* values in one input's delay line (linear_history) */
#define TB_MAX_MEMBERS 8u        /* models in an ensemble */
#define TB_MIN_LUMPED_STEP_S ((tb_real)1.0) /* shortest grid step of a lumped network (its state ring is 60 s / step) */
#define TB_MAX_LEVELS 64u
#define TB_MAX_CONDITIONS 64u
#define TB_MAX_FEEDS 64u /* distinct feeds in one classifier window */
#define TB_MAX_WINDOW 20000u /* samples in a classifier window or GRU history */
#define TB_START_SAMPLES 5u /* the limit filter checks the first reading against the next 5 */
#define TB_MAX_GAP_S ((tb_real)60.0)   /* longest gap between samples (the contract logs at >= 1 Hz) */
/* plausible inputs: anything beyond is refused (TB_E_INPUT), not computed with */
#define TB_MAX_AXIS_MM ((tb_real)1e7)
#define TB_MAX_FEED_MM_MIN ((tb_real)1e6)
#define TB_MAX_LOAD_N ((tb_real)1e9)
#define TB_MAX_OPERATING ((tb_real)1e9) /* |operating input| of a lumped network (e.g. spindle_rpm) */
#define TB_MAX_HEAT ((tb_real)1e30)     /* (u/u_ref)^p beyond it is refused */
#define TB_MIN_TEMP_C ((tb_real)-273.15)
#define TB_MAX_TEMP_C ((tb_real)2000.0)

/* model kinds */
enum {
    TB_KIND_MLR_CURVE = 1,  /* seed 002 eq. 6-11 / seed 004: curve coefficients linear in dT */
    TB_KIND_MLR_SEED001 = 2, /* seed 001 eq. 12 */
    TB_KIND_LSSVM = 3,      /* seed 002 eq. 12-14 (full or reduced set) */
    TB_KIND_MLP = 4,
    TB_KIND_GRU = 5,
    TB_KIND_PHYSICS = 6,    /* seed 000 §3.1-3.2 finite differences + effects */
    TB_KIND_AR = 7,         /* seed 003 ARX on operating parameters */
    TB_KIND_CLASSIFIER = 8, /* seed 002 eq. 15-19 proximity naive Bayes */
    TB_KIND_LUMPED = 9,     /* lumped thermal network of a spindle (docs/concepts.md, physics_spindle) */
    TB_KIND_THERMAL_LAG = 10, /* first-order lags of the rises and an operating input (thermal_lag) */
    /* 11: TB_KIND_ENVELOPE (a model's training envelope, not a model) */
    TB_KIND_LINEAR_HISTORY = 12, /* the rises now and delayed, from delay lines (linear_history) */
    TB_KIND_ENSEMBLE = 13,  /* a weighted sum of models of the other kinds, carried in the file (ensemble) */
    TB_KIND_MAX = 13
};
/* not a model: a model's training envelope, read by tb_guard_open (src/tb_guard.c) */
#define TB_KIND_ENVELOPE 11u
/* not a model: the sensor checks and the correction's bounds, read by tb_faults_open (src/tb_faults.c);
 * a data kind above every model kind */
#define TB_KIND_FAULTS 64u

/* error codes (all < 0) */
enum {
    TB_OK = 0,
    TB_E_SIZE = -1,     /* truncated, or length disagrees with n_payload */
    TB_E_MAGIC = -2,
    TB_E_VERSION = -3,
    TB_E_KIND = -4,
    TB_E_CRC = -5,
    TB_E_DIMS = -6,     /* a dimension is absurd or disagrees with the payload layout */
    TB_E_NAN = -7,      /* NaN or infinity in the payload */
    TB_E_PAYLOAD = -8,  /* a value out of its domain (code, index, order, sign) */
    TB_E_ARENA = -9,    /* arena too small or misaligned */
    TB_E_STATE = -10,   /* call out of order (not opened/started, wrong kind) */
    TB_E_INPUT = -11,   /* bad sample: non-finite, time not increasing, too few temperatures */
    TB_E_SAMPLING = -12, /* the log is not sampled at the model's period */
    TB_E_LATE = -13,    /* query older than the runtime still holds */
    TB_E_NOTREADY = -14, /* no state yet (before the first samples) */
    TB_E_ARG = -15,
    TB_E_ALIGN = -16 /* the model file does not start on a 4-byte boundary (tb_model_open) */
};

const char *tb_strerror(int code);

/* one control cycle: one process-log sample */
typedef struct {
    tb_real t_s;
    tb_real axis_mm;
    tb_real feed_mm_min;
    tb_real load_N;
    /* the exported input channels, in manifest order: the temperature sensors (degC), then the
     * operating inputs that have no field here (manifest "operating", e.g. spindle_rpm of a
     * lumped network), each in its own unit */
    const tb_real *temps_C;
    uint32_t n_temps;
    int measuring; /* nonzero inside a measuring cycle (left out of the motion features) */
} tb_sample;

/* a parsed model: views into the file, plus its state once started */
typedef struct {
    const uint8_t *payload;
    uint32_t n_payload;
    uint16_t kind;
    uint32_t dims[TB_MAX_DIMS];
    /* offsets (in float32 values) of the parsed sections */
    uint32_t off[10]; /* section offsets (src/tb_internal.h: O_COUNT) */
    uint32_t n_sensors;
    uint32_t max_channel; /* largest temps_C index used + 1 */
    void *state;
    size_t state_bytes;
} tb_model;

int tb_crc32_check(const uint8_t *file, size_t len, uint32_t *crc_out);
int tb_model_open(tb_model *m, const uint8_t *file, size_t len);
size_t tb_model_arena_bytes(const tb_model *m);
int tb_model_start(tb_model *m, void *arena, size_t arena_bytes);
int tb_model_step(tb_model *m, const tb_sample *s);
int tb_model_finish(tb_model *m);
tb_real tb_model_ready_s(const tb_model *m);
/* thermal part and total (geometric + thermal) positioning error, um; compensation = -total */
int tb_model_predict(const tb_model *m, tb_real t_s, tb_real axis_mm, tb_real *thermal_um, tb_real *total_um);
tb_real tb_model_geometric_um(const tb_model *m, tb_real axis_mm);

/* classifier (kind TB_KIND_CLASSIFIER): the condition index in force at t (-1: none yet) */
int tb_classifier_label_at(const tb_model *clf, tb_real t_s, int32_t *label);

/* a per-condition bank (seed 002 §2.4-2.5): the classifier picks the member model */
typedef struct {
    tb_model *classifier;
    tb_model *members[TB_MAX_CONDITIONS];
    uint32_t n_members;
} tb_bank;

int tb_bank_init(tb_bank *b, tb_model *classifier, tb_model *const *members, uint32_t n_members);
/* swap in a newly loaded (opened and started) model for condition i: before the first sample,
 * or once the new model has been stepped with the same samples as the bank (TB_E_STATE otherwise) */
int tb_bank_set_member(tb_bank *b, uint32_t i, tb_model *member);
int tb_bank_step(tb_bank *b, const tb_sample *s);
int tb_bank_finish(tb_bank *b);
tb_real tb_bank_ready_s(const tb_bank *b);
int tb_bank_predict(const tb_bank *b, tb_real t_s, tb_real axis_mm, tb_real *thermal_um, tb_real *total_um,
                    int32_t *label);

/* online updates from probe readings (src/tb_probe.c; thermbench/bench/adapt.py): a Kalman filter on a
 * bias and a gain correction of the model's total error,
 *   measured = (1 + gain) * predicted + bias + v,  v ~ N(0, r_um2),
 * the bias and gain walking at random between probes (q_* per hour). The caller keeps the state
 * (one per model it corrects); nothing is allocated. Per probe reading (t, axis, measured error):
 *   tb_probe(&m, &f, t_s, axis_mm, measured_um);          predicts at (t, axis) and updates
 * and per cycle, the corrected prediction and its variance:
 *   tb_model_predict(&m, t_s, axis_mm, &thermal, &total);
 *   tb_probe_correct(&f, t_s, total, &corrected, &var);   compensation = -corrected */
typedef struct {
    tb_real q_bias_um2_per_h; /* the bias's random walk, um^2 per hour */
    tb_real q_gain_per_h;     /* the gain's, per hour */
    tb_real r_um2;            /* a reading's scatter (> 0) */
    tb_real bias0_um;         /* the bias's std before the first probe */
    tb_real gain0;            /* the gain's std before the first probe */
} tb_probe_params;

typedef struct {
    tb_probe_params p;
    tb_real bias_um, gain;    /* the correction */
    tb_real P00, P01, P11;    /* its covariance at t_s */
    tb_real t_s;              /* the state's time: the last probe's, or the start */
    uint32_t n_probes;
} tb_probe_state;

int tb_probe_init(tb_probe_state *f, const tb_probe_params *p, tb_real t0_s);
int tb_probe_correct(const tb_probe_state *f, tb_real t_s, tb_real predicted_um, tb_real *corrected_um, tb_real *var_um2);
/* TB_E_LATE for a probe older than the state's time */
int tb_probe_update(tb_probe_state *f, tb_real t_s, tb_real predicted_um, tb_real measured_um, tb_real *innovation_um);
int tb_probe(const tb_model *m, tb_probe_state *f, tb_real t_s, tb_real axis_mm, tb_real measured_um);

/* the extrapolation guard (src/tb_guard.c; thermbench/bench/intervals.py EnvelopeGuard): a model's
 * training envelope (the export's envelope.tbm, read in place) followed sample by sample. Per
 * control cycle, after tb_model_step with the same sample:
 *   tb_guard_step(&g, &sample, &distance);   distance > 0: EXTRAPOLATING (in widths of the range)
 * g.outside has bit i set for input i beyond its range (rise:<sensor>..., rate:<sensor>...,
 * op:<input>..., the envelope's order); tb_guard_reset starts again from the next sample (a model
 * restart). */
typedef struct {
    const uint8_t *payload;   /* the file's [tau_s, lo, hi, width], float32 */
    uint32_t n_sensors, n_operating;
    tb_real tau_s;
    tb_real T0_C[TB_MAX_SENSORS], e_C[TB_MAX_SENSORS]; /* first sample, exponential average */
    tb_real t_last_s;
    int started;
    tb_real distance;         /* the last sample's */
    uint32_t outside;         /* the last sample's inputs beyond their range (bit i, the first 32) */
} tb_guard;

int tb_guard_open(tb_guard *g, const uint8_t *file, size_t len);
void tb_guard_reset(tb_guard *g);
int tb_guard_step(tb_guard *g, const tb_sample *s, tb_real *distance);

/* sensor faults and the correction's bounds (src/tb_faults.c; thermbench/bench/faults.py FaultMonitor,
 * Bounds): the export's faults.tbm, read in place. Per control cycle, before tb_model_step:
 *   tb_faults_step(&f, &sample, temps);   the model reads temps (a faulty sensor as the others
 *                                         predict it) in place of sample.temps_C[0..n_sensors)
 *   f.faulty: bit i set once sensor i is judged faulty (SENSOR_FAULT), f.fault[i] the rule
 *   (TB_FAULT_*), f.onset_s[i] the sample's time; latched until tb_faults_reset (a model restart).
 * Per answer: tb_faults_bound(&f, &b, t_s, total_um, &bounded_um) returns 1 when a bound acted
 * (BOUNDED), one tb_bound per series of answers (a position along the axis). */
enum { TB_FAULT_NONE = 0, TB_FAULT_OPEN = 1, TB_FAULT_RANGE = 2, TB_FAULT_RATE = 3, TB_FAULT_STUCK = 4, TB_FAULT_OTHERS = 5 };
typedef struct {
    const uint8_t *payload;   /* the file's scalars, arrays and lines, float32 */
    uint32_t n_sensors;
    tb_real tau_s, max_um, rate_um_s; /* max_um, rate_um_s < 0: no such bound */
    tb_real T0_C[TB_MAX_SENSORS], e_C[TB_MAX_SENSORS], last_C[TB_MAX_SENSORS]; /* first reading, average, last */
    tb_real changed_s[TB_MAX_SENSORS], pac_K[TB_MAX_SENSORS]; /* when it last changed, the others' prediction then */
    tb_real trusted_C[TB_MAX_SENSORS], onset_s[TB_MAX_SENSORS];
    tb_real t_last_s;
    uint32_t faulty, trusted; /* bit i: sensor i judged faulty; has a trusted reading */
    uint8_t fault[TB_MAX_SENSORS];
    int started;
} tb_faults;
typedef struct {
    tb_real value_um, t_s; /* the series' last bounded value and its time */
    int started;
} tb_bound;

int tb_faults_open(tb_faults *f, const uint8_t *file, size_t len);
void tb_faults_reset(tb_faults *f);
int tb_faults_step(tb_faults *f, const tb_sample *s, tb_real *temps_C);
int tb_faults_bound(const tb_faults *f, tb_bound *b, tb_real t_s, tb_real value_um, tb_real *bounded_um);

#ifdef __cplusplus
}
#endif
#endif /* TB_RUNTIME_H */
