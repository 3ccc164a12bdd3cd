/*
 * tb_kind_mlp.c - kind MLP: a fully connected net on the standardised [dT..., position].
 * dims [S, L, activation]; body: in_mean[S + 1], in_scale[S + 1] (> 0), y_mean, y_scale (> 0);
 * O_A widths[L] (the last 1); O_B per layer W (out x in), b.
 */
#include "tb_internal.h"

enum { ACT_TANH = 1, ACT_RELU, ACT_GELU, ACT_SILU, ACT_SIGMOID };

static void parse(tbi_cur *c, tb_model *m, uint16_t version)
{
    uint32_t *d = m->dims, i, width = d[0] + 1, L = d[1];
    (void)version;
    if (d[0] > TB_MAX_SENSORS || L < 1 || L > TB_MAX_LAYERS || d[2] < ACT_TANH || d[2] > ACT_SIGMOID) {
        c->err = TB_E_DIMS;
        return;
    }
    tbi_parse_sensors(c, m, d[0]);
    tbi_parse_geom(c, m);
    m->off[O_BODY] = tbi_take(c, 2 * (d[0] + 1));
    for (i = 0; i <= d[0] && !c->err; i++)
        if (!(PV(m, m->off[O_BODY] + d[0] + 1 + i) > 0)) c->err = TB_E_PAYLOAD;
    tbi_take(c, 1);
    tbi_take_val(c, 0, 1e30f, 1); /* y scale > 0 */
    m->off[O_A] = c->pos; /* widths */
    for (i = 0; i < L && !c->err; i++) {
        uint32_t w = tbi_take_int(c, 1, TB_MAX_WIDTH);
        if (i == L - 1 && w != 1) c->err = TB_E_DIMS;
    }
    m->off[O_B] = c->pos; /* layers */
    for (i = 0; i < L && !c->err; i++) {
        uint32_t w = (uint32_t)PV(m, m->off[O_A] + i);
        tbi_take(c, w * width + w);
        width = w;
    }
}

static tb_real act(uint32_t code, tb_real x)
{
    switch (code) {
    case ACT_TANH: return tbm_tanh(x);
    case ACT_RELU: return x > 0 ? x : 0;
    case ACT_GELU: return TB_R(0.5) * x * (1 + tbm_erf(x / TB_R(1.41421356237309504880)));
    case ACT_SILU: return x * tbi_sigm(x);
    default: return tbi_sigm(x);
    }
}

static tb_real eval(const tb_model *m, const tb_real *dT, tb_real axis_mm)
{
    uint32_t S = m->dims[0], L = m->dims[1], body = m->off[O_BODY], l, i, j, width = S + 1, at = m->off[O_B];
    tb_real a[TB_MAX_WIDTH], b[TB_MAX_WIDTH];
    for (j = 0; j < S; j++) a[j] = (dT[j] - PV(m, body + j)) / PV(m, body + S + 1 + j);
    a[S] = (axis_mm - PV(m, body + S)) / PV(m, body + 2 * S + 1);
    for (l = 0; l < L; l++) {
        uint32_t w = (uint32_t)PV(m, m->off[O_A] + l);
        for (i = 0; i < w; i++) {
            tb_real s = PV(m, at + w * width + i);
            for (j = 0; j < width; j++) s += PV(m, at + i * width + j) * a[j];
            b[i] = l + 1 < L ? act(m->dims[2], s) : s;
        }
        at += w * width + w;
        width = w;
        for (i = 0; i < w; i++) a[i] = b[i];
    }
    return a[0] * PV(m, body + 2 * S + 3) + PV(m, body + 2 * S + 2);
}

const tbi_kind tbi_kind_mlp = {
    .kind = TB_KIND_MLP, .max_version = 1, .pipeline = 1, .parse = parse, .eval = eval,
};
