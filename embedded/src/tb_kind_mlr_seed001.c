/*
 * tb_kind_mlr_seed001.c - kind MLR_SEED001: seed 001 eq. 12, the error proportional to
 * (x - origin) with a slope polynomial in the first sensor's dT and linear in the second's.
 * dims [S = 2, m]; body: origin, a1 .. am, b1, c.
 */
#include "tb_internal.h"

static void parse(tbi_cur *c, tb_model *m, uint16_t version)
{
    uint32_t *d = m->dims;
    (void)version;
    if (d[0] != 2 || d[1] < 1 || d[1] > 8) { c->err = TB_E_DIMS; return; }
    tbi_parse_sensors(c, m, 2);
    tbi_parse_geom(c, m);
    m->off[O_BODY] = tbi_take(c, 1 + d[1] + 2);
}

static tb_real eval(const tb_model *m, const tb_real *dT, tb_real axis_mm)
{
    uint32_t deg = m->dims[1], body = m->off[O_BODY], i;
    tb_real s = 0, pw = 1;
    for (i = 1; i <= deg; i++) {
        pw *= dT[0];
        s += PV(m, body + i) * pw;
    }
    s += PV(m, body + deg + 1) * dT[1] + PV(m, body + deg + 2);
    return s * (axis_mm - PV(m, body));
}

const tbi_kind tbi_kind_mlr_seed001 = {
    .kind = TB_KIND_MLR_SEED001, .max_version = 1, .pipeline = 1, .parse = parse, .eval = eval,
};
