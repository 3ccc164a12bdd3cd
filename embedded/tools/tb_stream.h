/*
 * tb_stream.h - the text stream of the thermbench test drivers (tb_replay on the host,
 * tb_target_main on the Cortex-M4F): one process-log sample per 'S' line,
 *   S t_s axis_mm feed_mm_min load_N measuring T_0 ... T_{n-1}
 * Not part of the embedded runtime (it uses strtod).
 */
#ifndef TB_STREAM_H
#define TB_STREAM_H

#include "tb_runtime.h"

#include <stdlib.h>

/* Parse an 'S' line into s (temperatures into temps, at most max_temps); 0 when line is not a
   sample. s->temps_C points at temps. */
static int tb_parse_sample(const char *line, tb_sample *s, tb_real *temps, int max_temps)
{
    char *q = (char *)line + 1, *end;
    int n = 0;
    if (line[0] != 'S') return 0;
    s->t_s = (tb_real)strtod(q, &end); q = end;
    s->axis_mm = (tb_real)strtod(q, &end); q = end;
    s->feed_mm_min = (tb_real)strtod(q, &end); q = end;
    s->load_N = (tb_real)strtod(q, &end); q = end;
    s->measuring = (int)strtol(q, &end, 10); q = end;
    for (;;) {
        double v = strtod(q, &end);
        if (end == q || n == max_temps) break;
        temps[n++] = (tb_real)v;
        q = end;
    }
    s->temps_C = temps;
    s->n_temps = (uint32_t)n;
    return 1;
}

#endif
