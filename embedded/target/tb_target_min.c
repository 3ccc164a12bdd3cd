/*
 * tb_target_min.c - the smallest firmware that runs a model from flash: the runtime, the model
 * file, the start-up and this loop, without stdio (what a compensator's image needs at least;
 * thermbench.export.target.image measures its flash). It opens and starts the model, steps
 * TB_MIN_SAMPLES samples of a constant log at TB_MIN_PERIOD_S and predicts at the last one;
 * QEMU's exit status is 0 when open and start succeeded.
 */
#include "tb_runtime.h"

#ifndef TB_ARENA_BYTES
#define TB_ARENA_BYTES 16384
#endif
#ifndef TB_MIN_SAMPLES
#define TB_MIN_SAMPLES 8
#endif
#ifndef TB_MIN_PERIOD_S
#define TB_MIN_PERIOD_S 1.0
#endif

extern const uint8_t *const tb_files[];
extern const uint32_t tb_file_bytes[];

static uint64_t arena[(TB_ARENA_BYTES + 7) / 8];
static tb_model model;
volatile tb_real tb_min_out; /* kept: the prediction is used */

int main(void)
{
    tb_real temps[TB_MAX_SENSORS];
    tb_sample s;
    tb_real th = 0, tot = 0;
    int rc, i;
    rc = tb_model_open(&model, tb_files[0], tb_file_bytes[0]);
    if (rc != TB_OK) return 1;
    if (tb_model_arena_bytes(&model) > sizeof arena) return 2;
    rc = tb_model_start(&model, arena, sizeof arena);
    if (rc != TB_OK) return 3;
    for (i = 0; i < (int)TB_MAX_SENSORS; i++) temps[i] = 20.0;
    s.axis_mm = 100.0;
    s.feed_mm_min = 1000.0;
    s.load_N = 0.0;
    s.measuring = 1;
    s.temps_C = temps;
    s.n_temps = TB_MAX_SENSORS;
    for (i = 0; i < TB_MIN_SAMPLES; i++) {
        s.t_s = i * TB_MIN_PERIOD_S;
        (void)tb_model_step(&model, &s); /* a constant log: the samples may not suit every model */
    }
    (void)tb_model_predict(&model, s.t_s, 100.0, &th, &tot);
    tb_min_out = tot;
    return 0;
}
