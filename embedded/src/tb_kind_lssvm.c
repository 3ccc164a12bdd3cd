/*
 * tb_kind_lssvm.c - kind LSSVM: seed 002 eq. 12-14, an RBF kernel expansion
 * exp(-d^2 / (2 sigma^2)) on the standardised features [dT..., position] (full or reduced set).
 * dims [S, N]; body: mean[S + 1], scale[S + 1] (> 0), sigma2 (> 0), b (hi, lo); then
 * O_A alpha hi[N], lo[N] (float32 alone loses ~1e-8 |alpha|), O_B support vectors [N x (S + 1)].
 */
#include "tb_internal.h"

static void parse(tbi_cur *c, tb_model *m, uint16_t version)
{
    uint32_t *d = m->dims, i;
    (void)version;
    if (d[0] > TB_MAX_SENSORS || d[1] < 1 || d[1] > TB_MAX_SUPPORT) { c->err = TB_E_DIMS; return; }
    tbi_parse_sensors(c, m, d[0]);
    tbi_parse_geom(c, m);
    m->off[O_BODY] = tbi_take(c, 2 * (d[0] + 1));
    for (i = 0; i <= d[0] && !c->err; i++)
        if (!(PV(m, m->off[O_BODY] + d[0] + 1 + i) > 0)) c->err = TB_E_PAYLOAD;
    tbi_take_val(c, 0, 1e30f, 1); /* sigma2 > 0 */
    tbi_take(c, 2);               /* b as float32 hi + lo */
    m->off[O_A] = tbi_take(c, 2 * d[1]);
    m->off[O_B] = tbi_take(c, d[1] * (d[0] + 1));
}

static tb_real eval(const tb_model *m, const tb_real *dT, tb_real axis_mm)
{
    uint32_t S = m->dims[0], N = m->dims[1], d = S + 1, body = m->off[O_BODY], i, j;
    tb_real z[TB_MAX_SENSORS + 1], sigma2 = PV(m, body + 2 * d);
    tb_real acc = PV(m, body + 2 * d + 1), comp = PV(m, body + 2 * d + 2); /* b: hi, lo */
    tb_real inv2s = (tb_real)1 / (2 * sigma2);
    for (j = 0; j < S; j++) z[j] = (dT[j] - PV(m, body + j)) / PV(m, body + d + j);
    z[S] = ((tb_real)axis_mm - PV(m, body + S)) / PV(m, body + d + S);
    for (i = 0; i < N; i++) {
        tb_real d2 = 0;
        uint32_t at = m->off[O_B] + i * d;
        for (j = 0; j < d; j++) {
            tb_real e = z[j] - PV(m, at + j);
            d2 += e * e;
        }
        {
            /* Neumaier's compensated sum: the terms are large and cancel (a full LSSVM's alphas) */
            tb_real k = tbm_exp(-(d2 * inv2s));
            tb_real term = PV(m, m->off[O_A] + i) * k, t = acc + term;
            comp += (tbm_fabs(acc) >= tbm_fabs(term) ? (acc - t) + term : (term - t) + acc) + PV(m, m->off[O_A] + N + i) * k;
            acc = t;
        }
    }
    return acc + comp;
}

const tbi_kind tbi_kind_lssvm = {
    .kind = TB_KIND_LSSVM, .max_version = 1, .pipeline = 1, .parse = parse, .eval = eval,
};
