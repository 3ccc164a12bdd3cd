/*
 * libFuzzer target for the model-file loader and the runtime behind it.
 *
 *   make fuzz                     (clang -fsanitize=fuzzer,address,undefined)
 *
 * Every input is tried twice: as it is (so the header checks, the length check and the
 * CRC-32 are fuzzed) and with its payload count and CRC-32 patched to match (so the
 * mutations reach the payload parser). A file that opens is then started in an arena
 * and stepped through a few samples and queries, then through hostile samples made
 * from the input's own bytes (NaN, inf, huge values, time going back, gaps): a hostile
 * file or stream must give an error code, never an out-of-bounds access (ASan) or
 * undefined behaviour (UBSan, with float-cast-overflow).
 */
#include "tb_runtime.h"

#include <stdlib.h>
#include <string.h>

static uint64_t arena[(1u << 20) / 8];

static void exercise(const uint8_t *buf, size_t size)
{
    tb_model m;
    size_t need;
    int i;
    if (tb_model_open(&m, buf, size) != TB_OK) return;
    need = tb_model_arena_bytes(&m);
    if (need == 0 || need > sizeof arena) return;
    if (tb_model_start(&m, arena, sizeof arena) != TB_OK) return;
    for (i = 0; i < 40; i++) {
        double temps[64];
        tb_sample s;
        double th, tot;
        int k;
        for (k = 0; k < 64; k++) temps[k] = 20.0 + 0.01 * i + (k == 0 && i == 3 ? 60.0 : 0.0);
        s.t_s = (double)i;
        s.axis_mm = 100.0 + 10.0 * (i % 7);
        s.feed_mm_min = (i % 5) ? 3000.0 : 0.0;
        s.load_N = 500.0;
        s.temps_C = temps;
        s.n_temps = 64;
        s.measuring = (i % 11) == 0;
        if (tb_model_step(&m, &s) != TB_OK) break;
        if (m.kind != TB_KIND_CLASSIFIER) tb_model_predict(&m, (double)i - 0.5, s.axis_mm, &th, &tot);
    }
    for (i = 0; i + 32 <= (int)size && i < 32 * 8; i += 32) { /* hostile samples from the input's bytes */
        double v[4], temps[64], th, tot;
        tb_sample s;
        int k;
        memcpy(v, buf + i, sizeof v);
        for (k = 0; k < 64; k++) temps[k] = v[(k + 3) % 4];
        s.t_s = 40.0 + v[0];
        s.axis_mm = v[1];
        s.feed_mm_min = v[2];
        s.load_N = v[3];
        s.temps_C = temps;
        s.n_temps = (uint32_t)(buf[i] % 65);
        s.measuring = buf[i + 1] & 1;
        (void)tb_model_step(&m, &s);
        if (m.kind != TB_KIND_CLASSIFIER) (void)tb_model_predict(&m, v[0], v[1], &th, &tot);
    }
    tb_model_finish(&m);
    if (m.kind == TB_KIND_CLASSIFIER) {
        int32_t lab;
        tb_classifier_label_at(&m, 30.0, &lab);
    } else {
        double th, tot;
        tb_model_predict(&m, 39.0, 250.0, &th, &tot);
        (void)tb_model_geometric_um(&m, -1e9);
    }
}

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size)
{
    uint8_t *buf = (uint8_t *)malloc(size ? size : 1); /* exact size: ASan sees any over-read */
    if (!buf) return 0;
    memcpy(buf, data, size);
    exercise(buf, size);
    if (size >= TB_HEADER_BYTES + 4u && (size - TB_HEADER_BYTES - 4u) % 4u == 0) {
        uint32_t n = (uint32_t)((size - TB_HEADER_BYTES - 4u) / 4u), crc;
        buf[44] = (uint8_t)n;
        buf[45] = (uint8_t)(n >> 8);
        buf[46] = (uint8_t)(n >> 16);
        buf[47] = (uint8_t)(n >> 24);
        tb_crc32_check(buf, size - 4u, &crc);
        buf[size - 4] = (uint8_t)crc;
        buf[size - 3] = (uint8_t)(crc >> 8);
        buf[size - 2] = (uint8_t)(crc >> 16);
        buf[size - 1] = (uint8_t)(crc >> 24);
        exercise(buf, size);
    }
    free(buf);
    return 0;
}
