/*
 * tb_replay - host driver of the thermbench runtime (what thermbench replay and the
 * parity tests run). Not part of the embedded runtime: it may use stdio.
 *
 *   tb_replay --info FILE...               per file: kind, file bytes, state bytes
 *   tb_replay MODEL_FILE < stream          one model
 *   tb_replay --bank CLF M0 M1 ... < stream  a per-condition bank (members in class order)
 *   --lenient (first option): a sample the runtime refuses (bad value, off the sampling grid) is
 *   skipped, as a compensator would, and counted on stderr; otherwise it stops the replay
 *   --probe QB QG R B0 G0 (an option before the model): probe readings 'P' correct the model by the
 *   bias + gain filter of tb_probe (its tb_probe_params in that order); every query line then
 *   ends in the corrected total error and its variance
 *   --guard FILE (an option before the model, with --live): the extrapolation guard of tb_guard over
 *   the samples, FILE an envelope file (the export's envelope.tbm); every query line then ends in
 *   the guard's distance at the last sample before it (0 inside the envelope, nan before any)
 *   --faults FILE (an option before the model, with --live): the sensor checks and bounds of tb_faults,
 *   FILE a faults file (the export's faults.tbm); the model (and the guard) read each sample's
 *   temperatures as tb_faults_step gives them, and every query line then ends in the total error
 *   bounded (tb_faults_bound, one series per axis_mm), whether a bound acted (0/1), and the rule
 *   of each sensor so far, a digit per sensor (TB_FAULT_*: 0 healthy)
 *   --live (an option before the model): every query is answered with the samples up to its time
 *   only, before the next sample is stepped, as a compensator answers for the time it writes (a
 *   model whose values at t are final later, e.g. the screw physics between macro steps, gives its
 *   provisional value; one not ready yet gives its code)
 *
 * stream (text, one record per line):
 *   S t_s axis_mm feed_mm_min load_N measuring T_0 ... T_{n-1}   a process-log sample
 *   Q t_s axis_mm                                              a query (times nondecreasing)
 *   P t_s axis_mm measured_um                                  a probe reading (--probe; in time order
 *                                                              with the queries: a query at the same
 *                                                              time as a probe comes before it)
 * Every query is answered as soon as the runtime is ready for its time (tb_*_ready_s), the
 * rest after tb_*_finish at the end of the stream (--live: see above). Output, one line per query:
 *   t_s axis_mm thermal_um total_um label rc [corrected_um var_um2] [distance] [bounded_um bounded rules]
 * A probe prints nothing; one the runtime cannot answer yet (or refuses) is skipped and counted
 * on stderr.
 */
#include "tb_runtime.h"
#include "tb_stream.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#define MAX_FILES (TB_MAX_CONDITIONS + 1)
#define FILE_POOL (64u * 1024u * 1024u)
#define ARENA_POOL (64u * 1024u * 1024u)
#define MAX_TEMPS 64

static uint8_t file_pool[FILE_POOL];
static uint64_t arena_pool[ARENA_POOL / 8];

static tb_model models[MAX_FILES];
static size_t file_used, arena_used;

static int load(const char *path, tb_model *m, size_t *len_out)
{
    FILE *f = fopen(path, "rb");
    size_t n;
    int rc;
    if (!f) {
        fprintf(stderr, "tb_replay: cannot open %s\n", path);
        return 2;
    }
    n = fread(file_pool + file_used, 1, FILE_POOL - file_used, f);
    fclose(f);
    rc = tb_model_open(m, file_pool + file_used, n);
    if (rc != TB_OK) {
        fprintf(stderr, "tb_replay: %s: error %d: %s\n", path, rc, tb_strerror(rc));
        return 3;
    }
    file_used += (n + 7u) & ~(size_t)7u;
    if (len_out) *len_out = n;
    return 0;
}

static int start(tb_model *m)
{
    size_t need = tb_model_arena_bytes(m);
    int rc;
    if (arena_used + need + 8 > ARENA_POOL) return 4;
    rc = tb_model_start(m, (uint8_t *)arena_pool + arena_used, need);
    arena_used += (need + 7u) & ~(size_t)7u;
    if (rc != TB_OK) {
        fprintf(stderr, "tb_replay: start: error %d: %s\n", rc, tb_strerror(rc));
        return 4;
    }
    return 0;
}

typedef struct {
    double t, x, measured;
    int probe; /* a probe reading, not a query */
} query_t;

static query_t *queries;
static size_t n_q, q_done;

static tb_bank bank;
static int use_bank, lenient, live, probing, guarding, checking;
static tb_guard guard;
static tb_faults faults;
#define MAX_SERIES 256
static double series_x[MAX_SERIES];
static tb_bound series[MAX_SERIES];
static size_t n_series;
static unsigned long rejected, probes_skipped;
static tb_probe_state filt;

static tb_real ready(void) { return use_bank ? tb_bank_ready_s(&bank) : tb_model_ready_s(&models[0]); }

/* the end of an answer line: the guard's distance at the last sample stepped (--guard); the total
 * bounded in its series (the query's axis_mm), whether a bound acted, each sensor's rule (--faults) */
static void end_line(double t, double x, double total)
{
    if (guarding && guard.started) printf(" %.17g", (double)guard.distance);
    else if (guarding) printf(" nan");
    if (checking) {
        tb_real out = (tb_real)total;
        size_t k;
        uint32_t i;
        int acted = 0;
        for (k = 0; k < n_series && series_x[k] != x; k++) continue;
        if (k == n_series && n_series < MAX_SERIES) series_x[n_series++] = x;
        if (k < n_series) acted = tb_faults_bound(&faults, &series[k], (tb_real)t, (tb_real)total, &out);
        printf(" %.17g %d ", (double)out, acted > 0);
        for (i = 0; i < faults.n_sensors; i++) putchar('0' + faults.fault[i]);
        if (!faults.n_sensors) putchar('-');
    }
    printf("\n");
}

/* the queries up to time upto (all: every one left; before: strictly before upto, --live), each
 * with the runtime's answer, or TB_E_NOTREADY while it has no state yet (--live: the compensator
 * writes nothing then) */
static void answer_until(double upto, int all, int before)
{
    while (q_done < n_q && (all || (before ? queries[q_done].t < upto : queries[q_done].t <= upto))) {
        tb_real th = 0, tot = 0;
        int32_t lab = -1;
        int rc;
        if (live && !(ready() > (tb_real)-1e29)) {
            if (queries[q_done].probe) probes_skipped++;
            else {
                printf("%.17g %.17g nan nan -1 %d", queries[q_done].t, queries[q_done].x, TB_E_NOTREADY);
                if (probing) printf(" nan nan");
                end_line(queries[q_done].t, queries[q_done].x, NAN);
            }
            q_done++;
            continue;
        }
        if (use_bank) rc = tb_bank_predict(&bank, (tb_real)queries[q_done].t, (tb_real)queries[q_done].x, &th, &tot, &lab);
        else rc = tb_model_predict(&models[0], (tb_real)queries[q_done].t, (tb_real)queries[q_done].x, &th, &tot);
        if (queries[q_done].probe) {
            if (rc == TB_OK) rc = tb_probe_update(&filt, (tb_real)queries[q_done].t, tot, (tb_real)queries[q_done].measured, 0);
            if (rc != TB_OK) probes_skipped++;
        } else if (probing) {
            tb_real corr = 0, var = 0;
            if (rc == TB_OK) tb_probe_correct(&filt, (tb_real)queries[q_done].t, tot, &corr, &var);
            printf("%.17g %.17g %.17g %.17g %d %d %.17g %.17g", queries[q_done].t, queries[q_done].x, (double)th, (double)tot,
                   (int)lab, rc, (double)corr, (double)var);
            end_line(queries[q_done].t, queries[q_done].x, rc == TB_OK ? (double)corr : NAN);
        } else {
            printf("%.17g %.17g %.17g %.17g %d %d", queries[q_done].t, queries[q_done].x, (double)th, (double)tot, (int)lab, rc);
            end_line(queries[q_done].t, queries[q_done].x, rc == TB_OK ? (double)tot : NAN);
        }
        q_done++;
    }
}

static void answer(double upto, int all) { answer_until(upto, all, 0); }

int main(int argc, char **argv)
{
    int i, rc, n_files = 0;
    char line[8192];
    size_t cap_q = 1024;
    while (argc >= 2 && (strcmp(argv[1], "--lenient") == 0 || strcmp(argv[1], "--live") == 0 || strcmp(argv[1], "--probe") == 0 ||
                         strcmp(argv[1], "--guard") == 0 || strcmp(argv[1], "--faults") == 0)) {
        if (strcmp(argv[1], "--guard") == 0 || strcmp(argv[1], "--faults") == 0) {
            int is_guard = strcmp(argv[1], "--guard") == 0;
            FILE *f;
            size_t n;
            if (argc < 3) return 1;
            f = fopen(argv[2], "rb");
            if (!f) {
                fprintf(stderr, "tb_replay: cannot open %s\n", argv[2]);
                return 2;
            }
            n = fread(file_pool + file_used, 1, FILE_POOL - file_used, f);
            fclose(f);
            rc = is_guard ? tb_guard_open(&guard, file_pool + file_used, n) : tb_faults_open(&faults, file_pool + file_used, n);
            if (rc != TB_OK) {
                fprintf(stderr, "tb_replay: %s: error %d: %s\n", argv[2], rc, tb_strerror(rc));
                return 3;
            }
            file_used += (n + 7u) & ~(size_t)7u;
            if (is_guard) guarding = 1;
            else checking = 1;
            argv++;
            argc--;
        } else if (strcmp(argv[1], "--probe") == 0) {
            tb_probe_params pp;
            if (argc < 7) return 1;
            pp.q_bias_um2_per_h = (tb_real)strtod(argv[2], 0);
            pp.q_gain_per_h = (tb_real)strtod(argv[3], 0);
            pp.r_um2 = (tb_real)strtod(argv[4], 0);
            pp.bias0_um = (tb_real)strtod(argv[5], 0);
            pp.gain0 = (tb_real)strtod(argv[6], 0);
            probing = 1;
            if (tb_probe_init(&filt, &pp, 0) != TB_OK) {
                fprintf(stderr, "tb_replay: --probe: bad filter parameters\n");
                return 1;
            }
            argv += 5;
            argc -= 5;
        } else if (strcmp(argv[1], "--lenient") == 0) lenient = 1;
        else live = 1;
        argv++;
        argc--;
    }
    if (argc < 2) {
        fprintf(stderr, "usage: tb_replay [--lenient] [--live] [--probe QB QG R B0 G0] [--guard FILE] [--faults FILE] [--info FILE...] | MODEL | --bank CLF M0 M1 ...\n");
        return 1;
    }
    if (checking && !live) {
        fprintf(stderr, "tb_replay: --faults needs --live (a query's bound follows the samples up to it)\n");
        return 1;
    }
    if (guarding && !live) {
        fprintf(stderr, "tb_replay: --guard needs --live (a query's distance is that of the last sample before it)\n");
        return 1;
    }
    if (strcmp(argv[1], "--info") == 0) {
        for (i = 2; i < argc; i++) {
            size_t len = 0;
            tb_model m;
            if (load(argv[i], &m, &len)) return 3;
            printf("%s %d %lu %lu %lu\n", argv[i], (int)m.kind, (unsigned long)len,
                   (unsigned long)tb_model_arena_bytes(&m), (unsigned long)sizeof(tb_model));
        }
        return 0;
    }
    if (strcmp(argv[1], "--bank") == 0) {
        tb_model *members[TB_MAX_CONDITIONS];
        use_bank = 1;
        if (argc < 4 || argc - 2 > (int)MAX_FILES) return 1;
        for (i = 2; i < argc; i++) {
            if ((rc = load(argv[i], &models[n_files], 0)) != 0) return rc;
            if ((rc = start(&models[n_files])) != 0) return rc;
            n_files++;
        }
        for (i = 1; i < n_files; i++) members[i - 1] = &models[i];
        rc = tb_bank_init(&bank, &models[0], members, (uint32_t)(n_files - 1));
        if (rc != TB_OK) {
            fprintf(stderr, "tb_replay: bank: error %d: %s\n", rc, tb_strerror(rc));
            return 5;
        }
    } else {
        if ((rc = load(argv[1], &models[0], 0)) != 0) return rc;
        if ((rc = start(&models[0])) != 0) return rc;
    }
    queries = (query_t *)malloc(cap_q * sizeof(query_t));
    if (!queries) return 6;
    /* the queries may come anywhere in the stream: read everything first */
    {
        static char *lines_buf;
        size_t used = 0, cap = 1u << 20;
        char *p;
        lines_buf = (char *)malloc(cap);
        if (!lines_buf) return 6;
        while (fgets(line, sizeof line, stdin)) {
            size_t l = strlen(line);
            if (line[0] == 'Q' || (line[0] == 'P' && probing)) {
                if (n_q == cap_q) {
                    cap_q *= 2;
                    queries = (query_t *)realloc(queries, cap_q * sizeof(query_t));
                    if (!queries) return 6;
                }
                queries[n_q].probe = line[0] == 'P';
                queries[n_q].measured = 0;
                if (queries[n_q].probe) {
                    if (sscanf(line + 1, "%lf %lf %lf", &queries[n_q].t, &queries[n_q].x, &queries[n_q].measured) != 3) return 7;
                } else if (sscanf(line + 1, "%lf %lf", &queries[n_q].t, &queries[n_q].x) != 2) {
                    return 7;
                }
                if (n_q == 0) filt.t_s = (tb_real)queries[0].t; /* the filter starts at the first record */
                n_q++;
                continue;
            }
            if (used + l + 1 > cap) {
                while (used + l + 1 > cap) cap *= 2;
                lines_buf = (char *)realloc(lines_buf, cap);
                if (!lines_buf) return 6;
            }
            memcpy(lines_buf + used, line, l + 1);
            used += l + 1;
        }
        for (p = lines_buf; p < lines_buf + used; p += strlen(p) + 1) {
            tb_sample s;
            tb_real temps[MAX_TEMPS];
            if (!tb_parse_sample(p, &s, temps, MAX_TEMPS)) continue;
            if (live) answer_until((double)s.t_s, 0, 1); /* the queries this sample comes after */
            if (checking) { /* the model reads the temperatures as the sensor checks give them */
                tb_real read[TB_MAX_SENSORS];
                uint32_t k;
                if ((rc = tb_faults_step(&faults, &s, read)) != TB_OK) {
                    fprintf(stderr, "tb_replay: faults: sample t=%.17g: error %d: %s\n", (double)s.t_s, rc, tb_strerror(rc));
                    return 11;
                }
                for (k = 0; k < faults.n_sensors; k++) temps[k] = read[k];
            }
            rc = use_bank ? tb_bank_step(&bank, &s) : tb_model_step(&models[0], &s);
            if (rc != TB_OK && lenient && (rc == TB_E_INPUT || rc == TB_E_SAMPLING)) {
                rejected++;
                continue;
            }
            if (rc != TB_OK) {
                fprintf(stderr, "tb_replay: sample t=%.17g: error %d: %s\n", (double)s.t_s, rc, tb_strerror(rc));
                return 8;
            }
            if (guarding && (rc = tb_guard_step(&guard, &s, 0)) != TB_OK) {
                fprintf(stderr, "tb_replay: guard: sample t=%.17g: error %d: %s\n", (double)s.t_s, rc, tb_strerror(rc));
                return 10;
            }
            if (!live) answer(ready(), 0);
        }
        free(lines_buf);
    }
    if (live) answer(0, 1); /* after the last sample, before the end is known */
    rc = use_bank ? tb_bank_finish(&bank) : tb_model_finish(&models[0]);
    if (rc != TB_OK) return 9;
    if (rejected) fprintf(stderr, "tb_replay: %lu sample(s) refused and skipped\n", rejected);
    if (probes_skipped) fprintf(stderr, "tb_replay: %lu probe(s) not taken (no prediction at their time)\n", probes_skipped);
    answer(0, 1);
    free(queries);
    return 0;
}
