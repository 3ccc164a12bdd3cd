/*
 * tb_guard.c - the extrapolation guard: the training envelope of a model's inputs followed
 * sample by sample, as thermbench/bench/intervals.py (EnvelopeGuard) follows it. Allocation-free.
 *
 * Inputs, per sample: each sensor's rise above its first sample (K), its high-pass rate
 * (T - e) * 3600 / tau, e the exponential average e += (1 - exp(-dt / tau)) (T - e) (K/h), then
 * each operating input as it is. The distance of a sample is the largest exceedance of any input
 * beyond its range, in widths of that range (0 inside): beyond 0 the model extrapolates.
 *
 * The envelope file (written by the export, thermbench.export.fileformat, kind TB_KIND_ENVELOPE)
 * has the model file's header and CRC; dims = [n_sensors, n_operating], payload
 * [tau_s, lo[n], hi[n], width[n]] with n = 2 n_sensors + n_operating in the order
 * rise:<sensor>..., rate:<sensor>..., op:<input>... The sensors and operating inputs are the
 * model's, in the order of its samples' temps_C. The file is read in place.
 */
#include "tb_internal.h"

int tb_guard_open(tb_guard *g, const uint8_t *file, size_t len)
{
    uint32_t n_payload, n, i, dims[TB_MAX_DIMS];
    uint16_t version, kind;
    int rc;
    if (!g) return TB_E_ARG;
    memset(g, 0, sizeof *g);
    if (!file) return TB_E_ARG;
    if ((rc = tbi_check_file(file, len, &version, &kind, &n_payload)) != TB_OK) return rc;
    if (version != TB_FORMAT_VERSION) return TB_E_VERSION;
    if (kind != TB_KIND_ENVELOPE) return TB_E_KIND;
    if ((rc = tbi_check_dims(file, dims)) != TB_OK) return rc;
    if (tbi_rd_u16(file + 8) != 2u) return TB_E_DIMS;
    g->n_sensors = dims[0];
    g->n_operating = dims[1];
    if (g->n_sensors > TB_MAX_SENSORS || g->n_operating > TB_MAX_SENSORS) return TB_E_DIMS;
    n = 2u * g->n_sensors + g->n_operating;
    if (n_payload != 1u + 3u * n) return TB_E_DIMS;
    if ((rc = tbi_payload_finite(file + TB_HEADER_BYTES, n_payload)) != TB_OK) return rc;
    g->payload = file + TB_HEADER_BYTES;
    g->tau_s = (tb_real)tbi_rd_f32(g->payload);
    if (!(g->tau_s > 0)) {
        memset(g, 0, sizeof *g); /* a refused envelope guards nothing (tb_guard_step: TB_E_ARG) */
        return TB_E_PAYLOAD;
    }
    for (i = 0; i < n; i++) { /* lo <= hi, width > 0 */
        tb_real lo = (tb_real)tbi_rd_f32(g->payload + 4u * (1u + i));
        tb_real hi = (tb_real)tbi_rd_f32(g->payload + 4u * (1u + n + i));
        tb_real w = (tb_real)tbi_rd_f32(g->payload + 4u * (1u + 2u * n + i));
        if (!(lo <= hi) || !(w > 0)) {
            memset(g, 0, sizeof *g);
            return TB_E_PAYLOAD;
        }
    }
    return TB_OK;
}

void tb_guard_reset(tb_guard *g)
{
    if (!g) return;
    g->started = 0;
    g->distance = 0;
    g->outside = 0;
}

int tb_guard_step(tb_guard *g, const tb_sample *s, tb_real *distance)
{
    uint32_t ns, n, i;
    tb_real worst = 0;
    uint32_t outside = 0;
    if (!g || !g->payload || !s) return TB_E_ARG;
    ns = g->n_sensors;
    n = 2u * ns + g->n_operating;
    if (!isfinite(s->t_s) || s->n_temps < ns + g->n_operating || (ns + g->n_operating && !s->temps_C)) return TB_E_INPUT;
    for (i = 0; i < ns + g->n_operating; i++)
        if (!isfinite(s->temps_C[i])) return TB_E_INPUT;
    if (g->started && s->t_s < g->t_last_s) return TB_E_INPUT;
    if (!g->started) {
        for (i = 0; i < ns; i++) g->T0_C[i] = g->e_C[i] = s->temps_C[i];
        g->started = 1;
    } else if (s->t_s > g->t_last_s) {
        tb_real a = 1 - tbm_exp(-(s->t_s - g->t_last_s) / g->tau_s);
        for (i = 0; i < ns; i++) g->e_C[i] += a * (s->temps_C[i] - g->e_C[i]);
    }
    g->t_last_s = s->t_s;
    for (i = 0; i < n; i++) {
        tb_real f, over = 0, d;
        tb_real lo = (tb_real)tbi_rd_f32(g->payload + 4u * (1u + i));
        tb_real hi = (tb_real)tbi_rd_f32(g->payload + 4u * (1u + n + i));
        tb_real w = (tb_real)tbi_rd_f32(g->payload + 4u * (1u + 2u * n + i));
        if (i < ns) f = s->temps_C[i] - g->T0_C[i];
        else if (i < 2u * ns) f = (s->temps_C[i - ns] - g->e_C[i - ns]) * (TB_R(3600.0) / g->tau_s);
        else f = s->temps_C[i - ns];
        if (f > hi) over = f - hi;
        else if (f < lo) over = lo - f;
        if (over > 0 && i < 32u) outside |= 1u << i;
        d = over / w;
        if (d > worst) worst = d;
    }
    g->distance = worst;
    g->outside = outside;
    if (distance) *distance = worst;
    return TB_OK;
}
