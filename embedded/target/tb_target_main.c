/*
 * tb_target_main - the firmware-style test harness of the thermbench runtime on a Cortex-M4F
 * (QEMU mps2-an386, semihosting). The model files are linked into flash (models.S, written by
 * thermbench.export.target); the process log and the queries are read from the host through
 * semihosting, a line at a time (nothing of the stream is kept: RAM is 128 KB).
 *
 *   samples.txt   S t_s axis_mm feed_mm_min load_N measuring T_0 ... T_{n-1}   (tb_replay's records)
 *   queries.txt   Q t_s axis_mm, times nondecreasing; and, as tb_replay's options:
 *                 L                    (before any Q or P) answer live, as tb_replay --live
 *                 F QB QG R B0 G0      (before any Q or P) the probe filter tb_probe with these
 *                                      tb_probe_params, as tb_replay --probe; then
 *                 P t_s axis_mm measured_um   a probe reading, in time order with the queries (a
 *                                      query at a probe's time comes before it)
 *
 * One file: a model. Several: a per-condition bank, the classifier first (members in class
 * order). An envelope file linked beside them (tb_guard_file, tb_guard_bytes > 0: models.S) runs
 * the extrapolation guard tb_guard over the samples, as tb_replay --guard (it needs L); a faults file
 * (tb_faults_file, tb_faults_bytes > 0) the sensor checks and bounds of tb_faults, as tb_replay
 * --faults (it needs L; one bound series per axis_mm, at most MAX_SERIES). Every query
 * is answered as soon as the runtime is ready for its time, the rest after finish (L: with the
 * samples up to its time only). Output (semihosting stdout), one line per query as tb_replay's:
 *   t_s axis_mm thermal_um total_um label rc [corrected_um var_um2] [distance] [bounded_um bounded rules]
 * then a COUNT line per operation (below), "INFO key value ..." (the target's sizeof of the
 * runtime's structures, the probes taken and skipped) and "END rc stack_bytes arena_bytes": the
 * deepest stack of any runtime call (the stack is painted before each call and read after it) and
 * the arena the models took. Between TB_MARK_BEGIN and TB_MARK_END of each operation the harness
 * calls tb_target_mark (an instruction-count marker for the budget runs).
 */
#include "tb_runtime.h"
#include "../tools/tb_stream.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#ifndef TB_ARENA_BYTES
#define TB_ARENA_BYTES 16384
#endif
#define MAX_TEMPS 64

extern const uint8_t *const tb_files[];
extern const uint32_t tb_file_bytes[];
extern const uint32_t tb_n_files;
extern const uint8_t *const tb_guard_file; /* the envelope file (models.S), when tb_guard_bytes > 0 */
extern const uint32_t tb_guard_bytes;
extern const uint8_t *const tb_faults_file; /* the faults file (models.S), when tb_faults_bytes > 0 */
extern const uint32_t tb_faults_bytes;
extern void initialise_monitor_handles(void);
extern void tb_target_stack_repaint(void);
extern uint32_t tb_target_stack_below(uint32_t sp);

static uint64_t arena[(TB_ARENA_BYTES + 7) / 8];
static tb_model models[TB_MAX_CONDITIONS + 1];
static tb_bank bank;
static int use_bank, live, probing, guarding, checking;
static size_t arena_used;
static tb_probe_state filt;
static tb_guard guard;
static tb_faults faults;
#define MAX_SERIES 16
static double series_x[MAX_SERIES];
static tb_bound series[MAX_SERIES];
static uint32_t n_series;
static unsigned long probes_skipped;

/* semihosting exit and faults: tb_target_semihost.c; stdout is flushed before the exit */
void tb_target_flush(void) { fflush(stdout); }

/* ---- instruction counts ---------------------------------------------------------------
 * Under `qemu -icount shift=S` every instruction advances the virtual clock by 2^S ns, so the
 * SysTick counting the 25 MHz processor clock of the mps2-an386 ticks every 40 / 2^S instructions
 * (S = TB_ICOUNT_SHIFT, 0 to 3: QEMU must run with the same shift): a deterministic instruction
 * count of each runtime call, to 40 instructions (S = 0) or 5 (S = 3). */
#define SYST_CSR (*(volatile uint32_t *)0xE000E010u)
#define SYST_RVR (*(volatile uint32_t *)0xE000E014u)
#define SYST_CVR (*(volatile uint32_t *)0xE000E018u)
#ifndef TB_ICOUNT_SHIFT
#define TB_ICOUNT_SHIFT 0
#endif
#if TB_ICOUNT_SHIFT < 0 || TB_ICOUNT_SHIFT > 3
#error "TB_ICOUNT_SHIFT: 0 to 3 (40 >> shift instructions per SysTick tick)"
#endif
#define INSN_PER_TICK (40u >> TB_ICOUNT_SHIFT)
/* "finish": tb_*_finish at the stream's end (it integrates the last partial step: what it costs depends on
   where the stream ends), counted apart from the per-sample control cycle ("step"); "probe_update",
   "probe_correct": tb_probe_update per probe reading, tb_probe_correct per answer (the prediction before
   each is counted as "predict"); "guard_step": tb_guard_step per sample; "faults_step": tb_faults_step per
   sample, "faults_bound": tb_faults_bound per answer */
enum { MARK_END = 0, MARK_STEP = 1, MARK_PREDICT = 2, MARK_OPEN = 3, MARK_CALIBRATE = 4, MARK_FINISH = 5,
       MARK_PROBE_UPDATE = 6, MARK_PROBE_CORRECT = 7, MARK_GUARD_STEP = 8, MARK_FAULTS_STEP = 9, MARK_FAULTS_BOUND = 10,
       N_MARKS = 11 };
static const char *const mark_name[N_MARKS] = {"none", "step", "predict", "open", "calibrate", "finish",
                                               "probe_update", "probe_correct", "guard_step", "faults_step",
                                               "faults_bound"};
static uint32_t mark_at, mark_what;
static unsigned long mark_n[N_MARKS];
static double mark_sum[N_MARKS]; /* newlib-nano prints no long long */
static uint32_t mark_max[N_MARKS], mark_stack[N_MARKS]; /* the most instructions, the deepest stack (bytes) */

static void count_init(void)
{
    SYST_RVR = 0x00FFFFFFu;
    SYST_CVR = 0u;
    SYST_CSR = 5u; /* enabled, processor clock, no interrupt */
}

__attribute__((noinline)) void tb_target_mark(int what)
{
    uint32_t now = SYST_CVR; /* counts down, 24 bits */
    if (what != MARK_END) {
        mark_what = (uint32_t)what;
        mark_at = now;
        return;
    }
    {
        uint32_t ticks = (mark_at - now) & 0x00FFFFFFu, insn = ticks * INSN_PER_TICK;
        mark_n[mark_what]++;
        mark_sum[mark_what] += (double)insn;
        if (insn > mark_max[mark_what]) mark_max[mark_what] = insn;
    }
}

/* the counter's own check: a loop of known length, 2 instructions (subs, bne) per iteration */
#define CALIBRATE_ITER 50000u
__attribute__((noinline)) static void count_calibrate(void)
{
    uint32_t n = CALIBRATE_ITER;
    tb_target_mark(MARK_CALIBRATE);
    __asm volatile("1: subs %0, %0, #1\n\t"
                   "bne 1b"
                   : "+r"(n)
                   :
                   : "cc");
    tb_target_mark(MARK_END);
}

static void count_report(void)
{
    int k;
    for (k = 1; k < N_MARKS; k++)
        printf("COUNT %s %lu %.0f %lu %lu\n", mark_name[k], mark_n[k], mark_sum[k], (unsigned long)mark_max[k],
               (unsigned long)mark_stack[k]);
}

/* With TB_TRAP_UNALIGNED, an unaligned halfword or word access faults (CCR.UNALIGN_TRP) inside
   the runtime's calls: the alignment tests. Only there: newlib's own stdio reads unaligned. */
static void rt_trap(int on)
{
#ifdef TB_TRAP_UNALIGNED
    volatile uint32_t *ccr = (volatile uint32_t *)0xE000ED14u;
    if (on) *ccr |= (1u << 3);
    else *ccr &= ~(1u << 3);
    __asm volatile("dsb\n\tisb" ::: "memory");
#else
    (void)on;
#endif
}

/* the runtime's own stack: the deepest any runtime call went below the harness's frame (and per operation) */
static uint32_t rt_sp, rt_stack_max;

__attribute__((noinline)) static void rt_begin(int what)
{
    uint32_t sp;
    tb_target_stack_repaint();
    __asm volatile("mov %0, sp" : "=r"(sp));
    rt_sp = sp;
    rt_trap(1);
    tb_target_mark(what);
}

__attribute__((noinline)) static void rt_end(void)
{
    uint32_t used, what = mark_what;
    tb_target_mark(MARK_END);
    rt_trap(0);
    used = tb_target_stack_below(rt_sp);
    if (used > rt_stack_max) rt_stack_max = used;
    if (what < N_MARKS && used > mark_stack[what]) mark_stack[what] = used;
}

/* ---- queries and probe readings: read lazily, one ahead -------------------------------- */
static FILE *qf;
static int have_q, q_probe, q_first = 1, bad_header;
static double q_t, q_x, q_m;

static int next_query(void)
{
    char line[256];
    while (fgets(line, sizeof line, qf)) {
        if (line[0] == 'Q' && sscanf(line + 1, "%lf %lf", &q_t, &q_x) == 2) q_probe = 0;
        else if (line[0] == 'P' && probing && sscanf(line + 1, "%lf %lf %lf", &q_t, &q_x, &q_m) == 3) q_probe = 1;
        else if (line[0] == 'L' && q_first) {
            live = 1;
            continue;
        } else if (line[0] == 'F' && q_first) {
            double v[5];
            tb_probe_params pp;
            if (sscanf(line + 1, "%lf %lf %lf %lf %lf", &v[0], &v[1], &v[2], &v[3], &v[4]) != 5) {
                bad_header = 1;
                continue;
            }
            pp.q_bias_um2_per_h = (tb_real)v[0];
            pp.q_gain_per_h = (tb_real)v[1];
            pp.r_um2 = (tb_real)v[2];
            pp.bias0_um = (tb_real)v[3];
            pp.gain0 = (tb_real)v[4];
            if (tb_probe_init(&filt, &pp, 0) != TB_OK) bad_header = 1;
            else probing = 1;
            continue;
        } else continue;
        if (q_first && probing) filt.t_s = (tb_real)q_t; /* the filter starts at the first record, as tb_replay's */
        q_first = 0;
        return have_q = 1;
    }
    return have_q = 0;
}

static tb_real ready(void) { return use_bank ? tb_bank_ready_s(&bank) : tb_model_ready_s(&models[0]); }

/* the end of an answer line: the guard's distance at the last sample stepped; the total bounded in its
   series (the query's axis_mm), whether a bound acted, each sensor's rule (tb_replay's) */
static void end_line(double t, double x, double total)
{
    if (guarding && guard.started) printf(" %.17g", (double)guard.distance);
    else if (guarding) printf(" nan");
    if (checking) {
        tb_real out = (tb_real)total;
        uint32_t k, i;
        int acted = 0;
        for (k = 0; k < n_series && series_x[k] != x; k++) continue;
        if (k == n_series && n_series < MAX_SERIES) series_x[n_series++] = x;
        if (k < n_series) {
            rt_begin(MARK_FAULTS_BOUND);
            acted = tb_faults_bound(&faults, &series[k], (tb_real)t, (tb_real)total, &out);
            rt_end();
        }
        printf(" %.17g %d ", (double)out, acted > 0);
        for (i = 0; i < faults.n_sensors; i++) putchar('0' + faults.fault[i]);
        if (!faults.n_sensors) putchar('-');
    }
    printf("\n");
}

/* the queries and probes up to time upto (all: every one left; before: strictly before upto, live),
   as tb_replay's answer_until: live, a query before the runtime has a state gets TB_E_NOTREADY and a
   probe then is skipped */
static void answer_until(double upto, int all, int before)
{
    while (have_q && (all || (before ? q_t < upto : q_t <= upto))) {
        tb_real th = 0, tot = 0;
        int32_t lab = -1;
        int rc;
        if (live && !(ready() > (tb_real)-1e29)) {
            if (q_probe) probes_skipped++;
            else {
                printf("%.17g %.17g nan nan -1 %d", q_t, q_x, TB_E_NOTREADY);
                if (probing) printf(" nan nan");
                end_line(q_t, q_x, (double)NAN);
            }
            next_query();
            continue;
        }
        rt_begin(MARK_PREDICT);
        if (use_bank) rc = tb_bank_predict(&bank, (tb_real)q_t, (tb_real)q_x, &th, &tot, &lab);
        else rc = tb_model_predict(&models[0], (tb_real)q_t, (tb_real)q_x, &th, &tot);
        rt_end();
        if (q_probe) {
            if (rc == TB_OK) {
                rt_begin(MARK_PROBE_UPDATE);
                rc = tb_probe_update(&filt, (tb_real)q_t, tot, (tb_real)q_m, 0);
                rt_end();
            }
            if (rc != TB_OK) probes_skipped++;
        } else {
            double bound_what = rc == TB_OK ? (double)tot : (double)NAN;
            printf("%.17g %.17g %.17g %.17g %d %d", q_t, q_x, (double)th, (double)tot, (int)lab, rc);
            if (probing) {
                tb_real corr = 0, var = 0;
                if (rc == TB_OK) {
                    rt_begin(MARK_PROBE_CORRECT);
                    tb_probe_correct(&filt, (tb_real)q_t, tot, &corr, &var);
                    rt_end();
                }
                printf(" %.17g %.17g", (double)corr, (double)var);
                if (rc == TB_OK) bound_what = (double)corr;
            }
            end_line(q_t, q_x, bound_what);
        }
        next_query();
    }
}

static void answer(double upto, int all) { answer_until(upto, all, 0); }

static void report(int rc)
{
    count_report();
    printf("INFO sizeof_tb_model %lu sizeof_tb_bank %lu sizeof_tb_probe_state %lu sizeof_tb_guard %lu sizeof_tb_faults %lu "
           "sizeof_tb_real %lu probes_taken %lu probes_skipped %lu\n",
           (unsigned long)sizeof(tb_model), (unsigned long)sizeof(tb_bank), (unsigned long)sizeof(tb_probe_state),
           (unsigned long)sizeof(tb_guard), (unsigned long)sizeof(tb_faults), (unsigned long)sizeof(tb_real),
           (unsigned long)filt.n_probes, probes_skipped);
    printf("END %d %lu %lu\n", rc, (unsigned long)rt_stack_max, (unsigned long)arena_used);
}

static int open_start(uint32_t i)
{
    size_t need;
    int rc;
    rt_begin(MARK_OPEN);
    rc = tb_model_open(&models[i], tb_files[i], tb_file_bytes[i]);
    rt_end();
    if (rc != TB_OK) {
        printf("END %d 0 0 open %s\n", rc, tb_strerror(rc));
        return rc;
    }
    need = tb_model_arena_bytes(&models[i]);
    if (arena_used + need > sizeof arena) {
        printf("END %d 0 %lu arena: the models need more than TB_ARENA_BYTES = %lu\n", TB_E_ARENA,
               (unsigned long)(arena_used + need), (unsigned long)sizeof arena);
        return TB_E_ARENA;
    }
    rt_begin(MARK_OPEN);
    rc = tb_model_start(&models[i], (uint8_t *)arena + arena_used, need);
    rt_end();
    arena_used += (need + 7u) & ~(size_t)7u;
    if (rc != TB_OK) printf("END %d 0 0 start %s\n", rc, tb_strerror(rc));
    return rc;
}

int main(void)
{
    char line[1024];
    FILE *sf;
    uint32_t i;
    int rc;
    initialise_monitor_handles();
    count_init();
    count_calibrate();
    if (tb_n_files < 1 || tb_n_files > TB_MAX_CONDITIONS + 1) return 1;
    for (i = 0; i < tb_n_files; i++)
        if ((rc = open_start(i)) != TB_OK) return 0; /* reported on the END line */
    if (tb_n_files > 1) {
        tb_model *members[TB_MAX_CONDITIONS];
        for (i = 1; i < tb_n_files; i++) members[i - 1] = &models[i];
        use_bank = 1;
        rt_begin(MARK_OPEN);
        rc = tb_bank_init(&bank, &models[0], members, tb_n_files - 1);
        rt_end();
        if (rc != TB_OK) {
            printf("END %d 0 0 bank %s\n", rc, tb_strerror(rc));
            return 0;
        }
    }
    if (tb_guard_bytes > 0) {
        rt_begin(MARK_OPEN);
        rc = tb_guard_open(&guard, tb_guard_file, tb_guard_bytes);
        rt_end();
        if (rc != TB_OK) {
            printf("END %d 0 0 guard %s\n", rc, tb_strerror(rc));
            return 0;
        }
        guarding = 1;
    }
    if (tb_faults_bytes > 0) {
        rt_begin(MARK_OPEN);
        rc = tb_faults_open(&faults, tb_faults_file, tb_faults_bytes);
        rt_end();
        if (rc != TB_OK) {
            printf("END %d 0 0 faults %s\n", rc, tb_strerror(rc));
            return 0;
        }
        checking = 1;
    }
    sf = fopen("samples.txt", "r");
    qf = fopen("queries.txt", "r");
    if (!sf || !qf) {
        printf("END -100 0 0 cannot open samples.txt / queries.txt\n");
        return 1;
    }
    next_query(); /* and the options before the first record */
    if (bad_header) {
        printf("END %d 0 0 queries.txt: F: bad probe filter parameters\n", TB_E_ARG);
        return 0;
    }
    if (checking && !live) {
        printf("END %d 0 0 the faults file needs L in queries.txt (a query's bound follows the samples up to it)\n", TB_E_ARG);
        return 0;
    }
    if (guarding && !live) {
        printf("END %d 0 0 the guard needs L in queries.txt (a query's distance is that of the last sample before it)\n",
               TB_E_ARG);
        return 0;
    }
    while (fgets(line, sizeof line, sf)) {
        tb_sample s;
        tb_real temps[MAX_TEMPS];
        if (!tb_parse_sample(line, &s, temps, MAX_TEMPS)) continue;
        if (live) answer_until((double)s.t_s, 0, 1); /* the queries this sample comes after */
        if (checking) { /* the model reads the temperatures as the sensor checks give them */
            tb_real read[TB_MAX_SENSORS];
            uint32_t k;
            rt_begin(MARK_FAULTS_STEP);
            rc = tb_faults_step(&faults, &s, read);
            rt_end();
            if (rc != TB_OK) {
                printf("END %d %lu %lu faults: sample t=%.17g %s\n", rc, (unsigned long)rt_stack_max,
                       (unsigned long)arena_used, (double)s.t_s, tb_strerror(rc));
                return 0;
            }
            for (k = 0; k < faults.n_sensors; k++) temps[k] = read[k];
        }
        rt_begin(MARK_STEP);
        rc = use_bank ? tb_bank_step(&bank, &s) : tb_model_step(&models[0], &s);
        rt_end();
        if (rc != TB_OK) {
            printf("END %d %lu %lu sample t=%.17g %s\n", rc, (unsigned long)rt_stack_max,
                   (unsigned long)arena_used, (double)s.t_s, tb_strerror(rc));
            return 0;
        }
        if (guarding) {
            rt_begin(MARK_GUARD_STEP);
            rc = tb_guard_step(&guard, &s, 0);
            rt_end();
            if (rc != TB_OK) {
                printf("END %d %lu %lu guard: sample t=%.17g %s\n", rc, (unsigned long)rt_stack_max,
                       (unsigned long)arena_used, (double)s.t_s, tb_strerror(rc));
                return 0;
            }
        }
        if (!live) answer(ready(), 0);
    }
    if (live) answer(0, 1); /* after the last sample, before the end is known */
    rt_begin(MARK_FINISH);
    rc = use_bank ? tb_bank_finish(&bank) : tb_model_finish(&models[0]);
    rt_end();
    answer(0, 1);
    report(rc);
    fclose(sf);
    fclose(qf);
    return 0;
}
