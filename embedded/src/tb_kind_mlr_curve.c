/*
 * tb_kind_mlr_curve.c - kind MLR_CURVE: seed 002 eq. 6-11, seed 004. The error curve over the
 * travel is a polynomial in (x - origin) whose coefficients are linear in the sensors' dT.
 * dims [S, D]; body: origin, coef[(D + 1) x (1 + S)] (row i: k_i0, k_i1 .. k_iS).
 */
#include "tb_internal.h"

static void parse(tbi_cur *c, tb_model *m, uint16_t version)
{
    uint32_t *d = m->dims;
    (void)version;
    if (d[0] > TB_MAX_SENSORS || d[1] > TB_MAX_POLY) { c->err = TB_E_DIMS; return; }
    tbi_parse_sensors(c, m, d[0]);
    tbi_parse_geom(c, m);
    m->off[O_BODY] = tbi_take(c, 1 + (d[1] + 1) * (d[0] + 1));
}

static tb_real eval(const tb_model *m, const tb_real *dT, tb_real axis_mm)
{
    uint32_t S = m->dims[0], D = m->dims[1], body = m->off[O_BODY], i, j;
    tb_real x = axis_mm - PV(m, body), pw = 1, out = 0;
    for (i = 0; i <= D; i++) {
        uint32_t row = body + 1 + i * (S + 1);
        tb_real c = PV(m, row);
        for (j = 0; j < S; j++) c += PV(m, row + 1 + j) * dT[j];
        out += c * pw;
        pw *= x;
    }
    return out;
}

const tbi_kind tbi_kind_mlr_curve = {
    .kind = TB_KIND_MLR_CURVE, .max_version = 1, .pipeline = 1, .parse = parse, .eval = eval,
};
