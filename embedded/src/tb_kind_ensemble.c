/*
 * tb_kind_ensemble.c - kind ENSEMBLE: a weighted sum of other models (thermbench/models/ensemble.py), each
 * a model of its own kind carried whole inside this file. The error at (t, x) is sum_i w_i total_i(t, x),
 * total_i member i's full prediction (thermal and geometric); its own geometric block is zero.
 * dims [N, K]: the members (1..TB_MAX_MEMBERS), and K the set of their kinds (bit k for kind k: what a firmware
 * image must carry to run the file, read from the header; checked against the members); body: w[N] R (>= 0), then per member: kind, layout version,
 * n_dims, dims[8], n_payload, and its payload (n_payload float32 values, as in its own file after the
 * header). A member is opened as its own file is (tb_model_open after the header and CRC: this file's
 * header and CRC cover it); it is not an ENSEMBLE and not the classifier. R: a float32 (hi, lo) pair.
 * Samples go to every member once each has accepted them (none is stepped when one refuses).
 */
#include "tb_internal.h"

#define TB_ENS_RECORD (4u + TB_MAX_DIMS) /* kind, version, n_dims, dims[8], n_payload */

typedef struct {
    tb_model *members; /* N, opened and started in this model's arena */
} ens_t;

/* member i's record at payload position pos: opened into mm (TB_OK) */
static int open_member(const tb_model *m, uint32_t pos, tb_model *mm)
{
    uint32_t d[TB_MAX_DIMS], i, n_dims = (uint32_t)PV(m, pos + 2u), kind = (uint32_t)PV(m, pos);
    if (kind == TB_KIND_ENSEMBLE || kind == TB_KIND_CLASSIFIER || n_dims > TB_MAX_DIMS) return TB_E_PAYLOAD;
    for (i = 0; i < TB_MAX_DIMS; i++) {
        d[i] = (uint32_t)PV(m, pos + 3u + i);
        if (i >= n_dims && d[i] != 0) return TB_E_DIMS;
    }
    return tbi_open_parts(mm, (uint16_t)kind, (uint16_t)PV(m, pos + 1u), d, m->payload + 4u * (pos + TB_ENS_RECORD),
                          (uint32_t)PV(m, pos + 3u + TB_MAX_DIMS));
}

static void parse(tbi_cur *c, tb_model *m, uint16_t version)
{
    uint32_t N = m->dims[0], i, j, max_channel = 0, kinds = 0;
    tb_model mm;
    (void)version;
    if (N < 1 || N > TB_MAX_MEMBERS) {
        c->err = TB_E_DIMS;
        return;
    }
    tbi_parse_sensors(c, m, 0);
    tbi_parse_geom(c, m);
    m->off[O_BODY] = c->pos; /* weights */
    for (i = 0; i < N && !c->err; i++) tbi_take_pair(c, 0, TB_R(1e6), 0);
    m->off[O_A] = c->pos; /* the first member's record */
    for (i = 0; i < N && !c->err; i++) {
        uint32_t at = c->pos, n;
        tbi_take_int(c, 1, TB_KIND_MAX); /* the record, each entry in range and integral */
        tbi_take_int(c, TB_FORMAT_VERSION, TBI_MAX_VERSION);
        tbi_take_int(c, 0, TB_MAX_DIMS);
        for (j = 0; j < TB_MAX_DIMS && !c->err; j++) tbi_take_int(c, 0, 0x7FFFFFu);
        n = tbi_take_int(c, 1, TB_MAX_PAYLOAD);
        if (c->err) return;
        tbi_take(c, n); /* its payload */
        if (c->err) return;
        if ((c->err = open_member(m, at, &mm)) != TB_OK) return;
        if (mm.max_channel > max_channel) max_channel = mm.max_channel;
        kinds |= 1u << mm.kind;
    }
    if (kinds != m->dims[1]) c->err = TB_E_DIMS; /* the header names exactly the kinds inside */
    m->max_channel = max_channel;
}

/* the record after the one at pos */
static uint32_t next_record(const tb_model *m, uint32_t pos)
{
    return pos + TB_ENS_RECORD + (uint32_t)PV(m, pos + 3u + TB_MAX_DIMS);
}

static void carve(const tb_model *m, tbi_arena *a, void **ks)
{
    uint32_t N = m->dims[0], i, pos = m->off[O_A];
    ens_t *r = (ens_t *)tbi_carve(a, sizeof(ens_t));
    tb_model *mm = (tb_model *)tbi_carve(a, sizeof(tb_model) * N);
    for (i = 0; i < N && !a->err; i++, pos = next_record(m, pos)) {
        tb_model tmp, *target = a->p ? &mm[i] : &tmp;
        size_t need;
        void *arena;
        if (open_member(m, pos, target) != TB_OK) {
            a->err = 1;
            return;
        }
        need = tb_model_arena_bytes(target);
        arena = tbi_carve(a, need);
        if (a->p && !a->err && tb_model_start(target, arena, need) != TB_OK) a->err = 1;
    }
    if (a->p && !a->err) r->members = mm;
    *ks = r;
}

static int step(const tb_model *m, void *ks, const tb_sample *s)
{
    ens_t *r = (ens_t *)ks;
    uint32_t N = m->dims[0], i;
    int rc;
    for (i = 0; i < N; i++) /* every member takes it, or none */
        if ((rc = tbi_check_sample(&r->members[i], s)) != TB_OK) return rc;
    for (i = 0; i < N; i++)
        if ((rc = tb_model_step(&r->members[i], s)) != TB_OK) return rc;
    return TB_OK;
}

static void finish(const tb_model *m, void *ks)
{
    ens_t *r = (ens_t *)ks;
    uint32_t i;
    for (i = 0; i < m->dims[0]; i++) tb_model_finish(&r->members[i]);
}

static tb_real ready_s(const tb_model *m, const void *ks, tb_real *horizon_s)
{
    const ens_t *r = (const ens_t *)ks;
    tb_real t = 0;
    uint32_t i;
    for (i = 0; i < m->dims[0]; i++) {
        tb_real ti = tb_model_ready_s(&r->members[i]);
        if (i == 0 || ti < t) t = ti;
    }
    if (horizon_s) *horizon_s = TB_MAX_GAP_S; /* a member further out than its own horizon answers NOTREADY */
    return t;
}

static int predict(const tb_model *m, const void *ks, tb_real t, tb_real axis_mm, tb_real *thermal)
{
    const ens_t *r = (const ens_t *)ks;
    tb_real sum = 0, total;
    uint32_t i;
    int rc;
    for (i = 0; i < m->dims[0]; i++) {
        if ((rc = tb_model_predict(&r->members[i], t, axis_mm, 0, &total)) != TB_OK) return rc;
        sum += PR(m, m->off[O_BODY] + 2u * i) * total;
    }
    *thermal = sum;
    return TB_OK;
}

const tbi_kind tbi_kind_ensemble = {
    .kind = TB_KIND_ENSEMBLE, .max_version = 1, .pipeline = 0, .parse = parse, .carve = carve, .step = step,
    .finish = finish, .ready_s = ready_s, .predict = predict,
};
