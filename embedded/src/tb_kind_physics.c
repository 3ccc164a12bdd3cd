/*
 * tb_kind_physics.c - kind PHYSICS: seed 000 §3.1-3.2 finite differences of the screw's
 * temperature, §4.1 heat model, §4.3 compensation table (the full-length error array of the
 * last two macro steps, interpolated in time and position); the same fine steps, step
 * averages (difference arrays) and SDIRK2 macro steps as thermbench.sim.kernels.macro_run.
 * The effects are plugins (tb_physics.h, tb_fx_<name>.c).
 *
 * dims [S (0/1: a measured ambient), n_nodes]. Payload v2, after the period, the sensor block
 * and the geometric block:
 *   O_BODY  the core: the PHY_NCORE values of P_* below (thermbench PHYSICS_CORE)
 *   O_A     n_effects (<= TBI_MAX_EFFECTS), then per effect, codes increasing, a section
 *           (code, n_params, params...) read by that effect (tb_registry.def)
 * Payload v1 (files of thermbench before effects were plugins): the core, then 22 fixed slots
 * (V1_* below) holding every effect's flag and parameters; read through the same effect tables
 * (phys_effects), off[O_A] = 0.
 */
#include "tb_physics.h"

/* the core block (v1: its first values) */
enum {
    P_DX, P_DT, P_PER_STEP, P_MACRO, P_NODES, P_NB, P_NUT_LEN, P_BEAR_LEN, P_L, P_CAP, P_COND, P_SIDE, P_END,
    P_ALPHA, P_K1, P_K2, P_K3, P_K4, P_PF, PHY_NCORE
};

/* ------------------------------------------------------------ effects */
typedef struct {
    const tbi_effect *fx;
    uint32_t at; /* payload index of its parameters */
} fx_ref;

/* v1: the effects' fixed slots after the core: each effect's flag (present when nonzero), then
 * its parameters in the order of its v2 section */
enum {
    V1_AMB_MODE = PHY_NCORE, V1_AMB_AMP, V1_AMB_PERIOD, V1_AMB_PHASE, V1_AMB_RATE, V1_FREE, V1_KF, V1_FREE_K,
    V1_MOTOR, V1_KMOTOR, V1_TAU_MOTOR, V1_K5, V1_LOAD, V1_K6, V1_FF, V1_KAPPA, V1_OD, V1_BETA, V1_NPARAM = 41
};

static const struct {
    uint8_t code, flag, first;
} V1_EFFECTS[] = {              /* in code order */
    {1, V1_AMB_MODE, V1_AMB_AMP}, /* ambient_drift: when the ambient mode is 2 (simulated) */
    {2, V1_K5, V1_K5},            /* quadratic_friction_heat: when k5 != 0 (v1 added k5 v^2 = +0 else) */
    {3, V1_LOAD, V1_K6},          /* load_dependent_heat */
    {4, V1_MOTOR, V1_KMOTOR},     /* motor_heat */
    {5, V1_FREE, V1_KF},          /* free_end_bearing_heat */
    {6, V1_FF, V1_KAPPA},         /* fixed_fixed_constraint */
    {7, V1_OD, V1_BETA},          /* origin_drift: beta, then the housing's 4 values */
};

/* does model m call any hook of effect e? (an ambient with a measured ambient: none) */
static int phys_uses(const tb_model *m, const tbi_effect *e)
{
    return (e->ambient_rise && m->dims[0] == 0) || e->nut_heat || e->fine || e->source || e->step_start ||
           e->step_end || e->elongation || e->offset;
}

/* the effects of a parsed model, in code order; returns their number */
static uint32_t phys_effects(const tb_model *m, fx_ref *out)
{
    uint32_t n = 0, i, at = m->off[O_A], b = m->off[O_BODY];
    if (at) { /* v2 */
        uint32_t ne = (uint32_t)PV(m, at);
        at++;
        for (i = 0; i < ne; i++) {
            out[n].fx = tbi_effect_of((uint32_t)PV(m, at));
            out[n++].at = at + 2u;
            at += 2u + (uint32_t)PV(m, at + 1u);
        }
        return n;
    }
    for (i = 0; i < sizeof V1_EFFECTS / sizeof V1_EFFECTS[0]; i++) {
        uint32_t code = V1_EFFECTS[i].code;
        int on = code == 1 ? PV(m, b + V1_AMB_MODE) == 2 : PV(m, b + V1_EFFECTS[i].flag) != 0;
        if (!on) continue;
        out[n].fx = tbi_effect_of(code);
        out[n++].at = b + V1_EFFECTS[i].first;
    }
    return n;
}

/* ------------------------------------------------------------ parse */
/* the core's domains (both versions) */
static int core_ok(const tb_model *m, uint32_t at)
{
    uint32_t n = m->dims[1];
    tb_real dx = PV(m, at + P_DX), dt = PV(m, at + P_DT);
    return !(!(dx > 0) || !(dt > 0) || PV(m, at + P_NODES) != (tb_real)n || !(PV(m, at + P_PER_STEP) >= 1) ||
             PV(m, at + P_PER_STEP) != tbm_floor(PV(m, at + P_PER_STEP)) || PV(m, at + P_PER_STEP) > TB_R(1e6) ||
             !(PV(m, at + P_MACRO) / PV(m, at + P_PER_STEP) >= (tb_real)1e-3) || PV(m, at + P_MACRO) > TB_R(1e5) ||
             PV(m, at + P_MACRO) < (tb_real)0.1 || (tb_real)n * PV(m, at + P_PER_STEP) > TB_R(4e6) ||
             !(tbm_fabs(PV(m, at + P_L) / dx - (tb_real)n) <= TB_R(0.5) + TB_R(1e-6) * (tb_real)n ||
               (n == 2 && PV(m, at + P_L) / dx < TB_R(2.5))) ||
             !(PV(m, at + P_NB) >= 0) || PV(m, at + P_NB) > (tb_real)n ||
             PV(m, at + P_NB) != tbm_floor(PV(m, at + P_NB)) || !(PV(m, at + P_NUT_LEN) > 0) ||
             !(PV(m, at + P_L) > 0) || !(PV(m, at + P_CAP) > 0) || !(PV(m, at + P_COND) >= 0) ||
             (PV(m, at + P_NB) > 0 && !(PV(m, at + P_BEAR_LEN) > 0)));
}

/* v1: the slots no effect validates (the ambient mode; the free-end nodes even when unused) */
static int v1_ok(const tb_model *m, uint32_t at)
{
    tb_real mode = PV(m, at + V1_AMB_MODE), k = PV(m, at + V1_FREE_K);
    return !(mode < 0 || mode != tbm_floor(mode) || mode > 2 || (mode == 1) != (m->dims[0] == 1) || !(k >= 0) ||
             k > (tb_real)m->dims[1] || k != tbm_floor(k));
}

static void parse(tbi_cur *c, tb_model *m, uint16_t version)
{
    uint32_t *d = m->dims, at, i, ne, prev = 0;
    fx_ref fx[TBI_MAX_EFFECTS];
    if (d[0] > 1 || d[1] < 2 || d[1] > TB_MAX_NODES) { c->err = TB_E_DIMS; return; }
    tbi_parse_sensors(c, m, d[0]);
    tbi_parse_geom(c, m);
    if (version == 1) {
        m->off[O_BODY] = at = tbi_take(c, V1_NPARAM);
        if (c->err) return;
        if (!core_ok(m, at) || !v1_ok(m, at)) { c->err = TB_E_PAYLOAD; return; }
        ne = phys_effects(m, fx); /* off[O_A] = 0: the v1 slots */
        for (i = 0; i < ne && !c->err; i++)
            if (!fx[i].fx || (fx[i].fx->validate && fx[i].fx->validate(m, fx[i].at) != TB_OK)) c->err = TB_E_PAYLOAD;
        return;
    }
    m->off[O_BODY] = at = tbi_take(c, PHY_NCORE);
    if (c->err) return;
    if (!core_ok(m, at)) { c->err = TB_E_PAYLOAD; return; }
    m->off[O_A] = c->pos; /* > 0: the v2 sections */
    ne = tbi_take_int(c, 0, TBI_MAX_EFFECTS);
    for (i = 0; i < ne && !c->err; i++) {
        uint32_t code = tbi_take_int(c, 1, TBI_MAX_EFFECT_CODE), np = tbi_take_int(c, 0, 255);
        const tbi_effect *e = tbi_effect_of(code);
        if (c->err) return;
        if (!e || code <= prev) { c->err = TB_E_PAYLOAD; return; } /* unknown, repeated or out of order */
        if (np != e->n_params) { c->err = TB_E_DIMS; return; }
        at = tbi_take(c, np);
        if (!c->err && e->validate && e->validate(m, at) != TB_OK) c->err = TB_E_PAYLOAD;
        prev = code;
    }
}

/* ------------------------------------------------------------ state */
#define PP(m, i) PV(m, (m)->off[O_BODY] + (i))

static void phys_params(const tb_model *m, uint32_t n, uint32_t per_step, tbi_phys_par *q)
{
    q->n = n;
    q->nb = (uint32_t)PP(m, P_NB);
    q->macro = PP(m, P_MACRO);
    q->dt = q->macro / (tb_real)per_step; /* as dt_s in Python */
    q->dx = PP(m, P_DX);
    q->half = PP(m, P_NUT_LEN) / 2;
    q->L = PP(m, P_L);
    q->pf = PP(m, P_PF);
    q->sign = q->pf <= 0 ? 1 : -1;
    q->per_node = q->dx / PP(m, P_NUT_LEN);
    q->k1 = PP(m, P_K1);
    q->k2 = PP(m, P_K2);
    q->k3 = PP(m, P_K3);
    q->k4 = PP(m, P_K4);
    q->cap = PP(m, P_CAP);
    q->cond = PP(m, P_COND);
    q->side = PP(m, P_SIDE);
    q->end = PP(m, P_END);
    q->bear_len = PP(m, P_BEAR_LEN);
}

static void carve(const tb_model *m, tbi_arena *a, void **ks)
{
    uint32_t n = m->dims[1], i, k, ne;
    fx_ref ref[TBI_MAX_EFFECTS];
    tbi_phys *p = (tbi_phys *)tbi_carve(a, sizeof(tbi_phys));
    tb_real *arr = (tb_real *)tbi_carve(a, sizeof(tb_real) * (6u * n + 4u * (n + 1u)));
    tbi_fx *fx;
    void *self[TBI_MAX_EFFECTS];
    ne = phys_effects(m, ref);
    for (i = k = 0; i < ne; i++) /* the ones it never calls take no memory */
        if (phys_uses(m, ref[i].fx)) ref[k++] = ref[i];
    ne = k;
    fx = ne ? (tbi_fx *)tbi_carve(a, sizeof(tbi_fx) * ne) : 0;
    for (i = 0; i < ne; i++) self[i] = tbi_carve(a, ref[i].fx->self_bytes ? ref[i].fx->self_bytes : 1u);
    *ks = p;
    if (!a->p || a->err) return;
    p->n = n;
    p->per_step = (uint32_t)PP(m, P_PER_STEP);
    p->theta = arr;
    p->diag = arr + n;
    p->rhs = arr + 2 * n;
    p->y1 = arr + 3 * n;
    p->y2 = arr + 4 * n;
    p->cp = arr + 5 * n;
    p->q_nut = arr + 6 * n;      /* n + 1 */
    p->h_cov = arr + 7 * n + 1;  /* n + 1 */
    p->snap_u = arr + 8 * n + 2; /* 2 (n + 1) */
    p->fx = fx;
    p->n_fx = (uint8_t)ne;
    if (ne) {
        tbi_phys_par c;
        phys_params(m, n, p->per_step, &c);
        for (i = 0; i < ne; i++) {
            const tbi_effect *e = ref[i].fx;
            fx[i].fx = e;
            fx[i].self = self[i];
            if (e->init) e->init(self[i], m, ref[i].at, &c);
            if (e->ambient_rise && !p->amb && m->dims[0] == 0) p->amb = &fx[i];
            if (e->nut_heat) p->nut[p->n_nut++] = (uint8_t)i;
            if (e->fine) p->fine[p->n_fine++] = (uint8_t)i;
        }
    }
}

/* ------------------------------------------------------------ update */
static void phys_snapshot(const tb_model *m, tbi_phys *p, tb_real t_b, tb_real dta_b)
{
    uint32_t i, n = p->n, e;
    int s = p->n_snap == 0 ? 0 : 1 - p->snap_cur, any = 0;
    tb_real *u = p->snap_u + (size_t)s * (n + 1);
    tb_real alpha = PP(m, P_ALPHA), dx = PP(m, P_DX), off = 0;
    u[0] = 0;
    for (i = 0; i < n; i++) u[i + 1] = u[i] + alpha * (p->theta[i] - dta_b) * dx * (tb_real)1e6;
    for (e = 0; e < p->n_fx; e++) {
        const tbi_fx *f = &p->fx[e];
        if (f->fx->elongation) f->fx->elongation(f->self, u, n);
        if (f->fx->offset) {
            tb_real v = f->fx->offset(f->self);
            off = any ? off + v : v;
            any = 1;
        }
    }
    p->snap_t[s] = t_b;
    p->snap_amb[s] = dta_b;
    p->snap_off[s] = off;
    p->snap_cur = s;
    if (p->n_snap < 2) p->n_snap++;
}

static void solve_tridiag(uint32_t n, const tb_real *diag, tb_real off, const tb_real *rhs, tb_real *out,
                          tb_real *cprime)
{
    uint32_t i;
    tb_real b0 = diag[0];
    cprime[0] = off / b0;
    out[0] = rhs[0] / b0;
    for (i = 1; i < n; i++) {
        tb_real mm = diag[i] - off * cprime[i - 1];
        cprime[i] = off / mm;
        out[i] = (rhs[i] - off * out[i - 1]) / mm;
    }
    for (i = n - 1; i-- > 0;) out[i] -= cprime[i] * out[i + 1];
}

/* one macro step: step averages -> SDIRK2 (the same scheme as thermbench.sim.kernels.macro_run);
 * the nut heat and cover arrive as difference arrays (thermbench.sim.kernels.accumulate_step_averages) */
static void phys_macro(const tbi_phys_par *c, tbi_phys *p)
{
    uint32_t i, e, n = c->n, nb = c->nb;
    tb_real inv = (tb_real)1 / (tb_real)p->per_step;
    tb_real h_mean = p->h_sum * inv, qb_mean = p->qb_sum * inv, ta = p->dta_sum * inv;
    tb_real gamma = (tb_real)(1.0 - sqrt(2.0) / 2.0), gh = gamma * (tb_real)c->macro, off = -gh * c->cond;
    tb_real c1 = (1 - gamma) / gamma, qa = 0, ha = 0;
    tb_real *q = p->q_nut, *g = p->h_cov; /* difference arrays in, step averages out (in place) */
    for (i = 0; i < n; i++) {
        tb_real area = c->side + (i == n - 1 ? c->end : 0);
        if (i < nb) area = 0;
        qa += q[i];
        ha += g[i];
        q[i] = qa * inv;
        if (i < nb) q[i] += qb_mean * c->dx / c->bear_len;
        g[i] = (h_mean - ha * inv) * area;
    }
    for (e = 0; e < p->n_fx; e++)
        if (p->fx[e].fx->source) p->fx[e].fx->source(p->fx[e].self, q, n, inv);
#ifdef TB_SINGLE
    /* in float, in increments (the same SDIRK2): with M = C + gh A, M (y1 - theta) = gh (q + g ta - A theta)
     * = r and M (y2 - theta) = C c1 (y1 - theta) + r, so the step's small change is solved for, not the
     * field, of which float keeps 7 digits: solving for the field drifted by 2e-4 of the error over
     * 4-h runs (0.016 um at 78 um on the seed001 benchmark model), in increments 0.0016 um (the host float
     * build against Python over the same held-out runs; tests/test_export.py holds every family to 0.01 um) */
    for (i = 0; i < n; i++) {
        tb_real nbh = (i == 0 || i == n - 1) ? 1 : 2;
        tb_real nb_sum = (i > 0 ? p->theta[i - 1] : 0) + (i + 1 < n ? p->theta[i + 1] : 0);
        tb_real a_theta = (nbh * c->cond + g[i]) * p->theta[i] - c->cond * nb_sum;
        p->diag[i] = c->cap + gh * (nbh * c->cond + g[i]);
        p->rhs[i] = gh * (q[i] + g[i] * ta - a_theta);
        p->y2[i] = p->rhs[i]; /* r, kept for the second stage */
    }
    solve_tridiag(n, p->diag, off, p->rhs, p->y1, p->cp);
    for (i = 0; i < n; i++) p->rhs[i] = c->cap * c1 * p->y1[i] + p->y2[i];
    solve_tridiag(n, p->diag, off, p->rhs, p->y2, p->cp);
    for (i = 0; i < n; i++) p->theta[i] += p->y2[i];
#else
    /* in double, for the field as thermbench.sim.kernels does (the same operations in the same order) */
    for (i = 0; i < n; i++) {
        tb_real nbh = (i == 0 || i == n - 1) ? 1 : 2;
        p->diag[i] = c->cap + gh * (nbh * c->cond + g[i]);
        p->rhs[i] = c->cap * p->theta[i] + gh * (q[i] + g[i] * ta);
    }
    solve_tridiag(n, p->diag, off, p->rhs, p->y1, p->cp);
    for (i = 0; i < n; i++) p->rhs[i] = c->cap * (p->theta[i] + c1 * (p->y1[i] - p->theta[i])) + gh * (q[i] + g[i] * ta);
    solve_tridiag(n, p->diag, off, p->rhs, p->y2, p->cp);
    for (i = 0; i < n; i++) p->theta[i] = p->y2[i];
#endif
    for (e = 0; e < p->n_fx; e++)
        if (p->fx[e].fx->step_end) p->fx[e].fx->step_end(p->fx[e].self, c, p, qb_mean, p->v_sum * inv);
    for (i = 0; i <= n; i++) {
        q[i] = 0;
        g[i] = 0;
    }
    p->h_sum = p->qb_sum = p->dta_sum = p->v_sum = 0;
    p->k++;
}

/* the ambient's rise at t: the measured one (an ambient sensor), an effect's, or none */
static tb_real phys_ambient_rise(const tb_model *m, const tbi_phys *p, tb_real t, tb_real meas_rise)
{
    if (m->dims[0] == 1) return meas_rise;
    if (p->amb) return p->amb->fx->ambient_rise(p->amb->self, t - p->t0);
    return 0;
}

/* add value x cover to the difference array d (thermbench.sim.kernels._add_cover) */
static void add_cover(tb_real *d, tbi_int lo, tbi_int hi, tb_real w_lo, tb_real w_hi, tb_real v)
{
    d[lo] += v;
    d[hi + 1] -= v;
    d[lo] -= v * (1 - w_lo);
    d[lo + 1] += v * (1 - w_lo);
    if (hi != lo) {
        d[hi] -= v * (1 - w_hi);
        d[hi + 1] += v * (1 - w_hi);
    }
}

/* fine steps with times <= t_hi (inclusive), values interpolated from the previous sample to
 * (t_hi, x, f, load, amb) as numpy.interp over the log; stops at j_stop. The steps go in runs of
 * at most PHYS_RUN within one macro step: their inputs first, then the effects' per-step hooks
 * once per run (the same arithmetic, step by step, as one call per step) */
#define PHYS_RUN 16u
static void phys_fine(const tb_model *m, tbi_phys *p, tb_real t_hi, tb_real x1, tb_real f1, tb_real l1, tb_real a1,
                      tbi_count j_stop)
{
    tbi_phys_par c;
    tb_real span = t_hi - p->prev_t;
    tb_real sx, sf, sl, sa;
    tb_real r_axis[PHYS_RUN], r_v[PHYS_RUN], r_load[PHYS_RUN], r_amb[PHYS_RUN], r_qn[PHYS_RUN];
    int measured = m->dims[0] == 1;
    phys_params(m, p->n, p->per_step, &c);
    /* the slopes of numpy.interp between the previous sample and this one, computed once */
    sx = span > 0 ? (x1 - p->prev_x) / span : 0;
    sf = span > 0 ? (f1 - p->prev_f) / span : 0;
    sl = span > 0 ? (l1 - p->prev_load) / span : 0;
    sa = span > 0 ? (a1 - p->prev_amb) / span : 0;
    for (;;) {
        uint32_t r, cnt = 0, e;
        if (p->pending_snap) break; /* the boundary ambient is not known yet */
        while (cnt < PHYS_RUN) { /* the run's inputs */
            tbi_count j = p->j + cnt;
            tb_real tf = p->t0 + (tb_real)j * c.dt;
            tb_real u, amb;
            if (j >= j_stop || tf > t_hi) break;
            if (tf <= p->prev_t || span <= 0) {
                u = 0;
            } else {
                u = tf - p->prev_t;
            }
            if (tf >= t_hi && span > 0) {
                r_axis[cnt] = x1;
                r_v[cnt] = tbm_fabs(f1);
                r_load[cnt] = l1;
                amb = a1;
            } else {
                r_axis[cnt] = p->prev_x + u * sx;
                r_v[cnt] = tbm_fabs(p->prev_f + u * sf);
                r_load[cnt] = p->prev_load + u * sl;
                amb = p->prev_amb + u * sa;
            }
            r_amb[cnt] = measured ? amb : phys_ambient_rise(m, p, tf, amb);
            cnt++;
            if ((j + 1u) % p->per_step == 0) break; /* the macro step ends */
        }
        if (cnt == 0) break;
        if (p->j % p->per_step == 0) { /* step start */
            for (e = 0; e < p->n_fx; e++)
                if (p->fx[e].fx->step_start) p->fx[e].fx->step_start(p->fx[e].self, &c, p);
            p->amb_b_start = p->k == 0 ? 0 : p->snap_amb[p->snap_cur];
        }
        for (r = 0; r < cnt; r++) r_qn[r] = c.k4 * r_v[r]; /* QN = k4 v + the effects' nut heat */
        for (e = 0; e < p->n_nut; e++) {
            const tbi_fx *f = &p->fx[p->nut[e]];
            f->fx->nut_heat(f->self, r_v, r_load, r_qn, cnt);
        }
        for (r = 0; r < cnt; r++) {
            tb_real v = r_v[r], xs, h, qb, a, b;
            xs = c.sign * (r_axis[r] / (tb_real)1000 - c.pf);
            if (xs < 0) xs = 0;
            if (xs > c.L) xs = c.L;
            h = c.k1 * v + c.k2;
            qb = c.k3 * v;
            /* nut cover (thermbench.sim.kernels._nut_cover) */
            a = xs - c.half;
            b = xs + c.half;
            if (a < (tb_real)c.nb * c.dx) a = (tb_real)c.nb * c.dx;
            if (b > (tb_real)c.n * c.dx) b = (tb_real)c.n * c.dx;
            if (b > a) {
                tbi_int lo = tbi_floor_clamp(a / c.dx, 0, (tbi_int)c.n - 1);
                tbi_int hi = tbi_floor_clamp(b / c.dx, 0, (tbi_int)c.n - 1);
                tb_real w_lo, w_hi;
                if (lo == hi) {
                    w_lo = w_hi = (b - a) / c.dx;
                } else {
                    w_lo = (tb_real)(lo + 1) - a / c.dx;
                    w_hi = b / c.dx - (tb_real)hi;
                }
                add_cover(p->q_nut, lo, hi, w_lo, w_hi, r_qn[r] * c.per_node);
                add_cover(p->h_cov, lo, hi, w_lo, w_hi, h);
            }
            p->h_sum += h;
            p->qb_sum += qb;
            p->dta_sum += r_amb[r];
            p->v_sum += v;
        }
        for (e = 0; e < p->n_fine; e++) {
            const tbi_fx *f = &p->fx[p->fine[e]];
            f->fx->fine(f->self, r_v, cnt);
        }
        p->j += cnt;
        if (p->j % p->per_step == 0) {
            phys_macro(&c, p);
            p->pending_snap = 1;
        }
        if (p->pending_snap) {
            tb_real t_b = p->t0 + (tb_real)p->k * c.macro;
            if (t_b <= t_hi) {
                tb_real amb_b = phys_ambient_rise(m, p, t_b, tbi_interp1(t_b, p->prev_t, t_hi, p->prev_amb, a1));
                phys_snapshot(m, p, t_b, amb_b);
                p->pending_snap = 0;
            }
        }
    }
}

static void sample(const tb_model *m, void *ks, const tbi_motion *mo, const tb_real *dT)
{
    tbi_phys *p = (tbi_phys *)ks;
    tb_real amb = m->n_sensors ? dT[0] : 0;
    if (!p->have_t0) {
        p->have_t0 = 1;
        p->t0 = mo->t_s;
        p->prev_t = mo->t_s;
        p->prev_x = mo->axis_mm;
        p->prev_f = mo->feed_mm_min;
        p->prev_load = mo->load_N;
        p->prev_amb = amb;
        phys_snapshot(m, p, mo->t_s, phys_ambient_rise(m, p, mo->t_s, amb)); /* theta = 0 at t0 */
    }
    if (p->pending_snap) { /* the boundary of the last step lies before this sample */
        tb_real t_b = p->t0 + (tb_real)p->k * PP(m, P_MACRO);
        if (t_b <= mo->t_s) {
            tb_real amb_b = phys_ambient_rise(
                m, p, t_b, tbi_interp1(t_b, p->prev_t, mo->t_s, p->prev_amb, amb));
            phys_snapshot(m, p, t_b, amb_b);
            p->pending_snap = 0;
        }
    }
    phys_fine(m, p, mo->t_s, mo->axis_mm, mo->feed_mm_min, mo->load_N, amb, (tbi_count)-1);
    p->prev_t = mo->t_s;
    p->prev_x = mo->axis_mm;
    p->prev_f = mo->feed_mm_min;
    p->prev_load = mo->load_N;
    p->prev_amb = amb;
}

static void finish(const tb_model *m, void *ks)
{
    /* thermbench integrates ceil(span / macro) whole steps, the log's last values held */
    tbi_phys *p = (tbi_phys *)ks;
    tb_real macro = PP(m, P_MACRO);
    tbi_count j_stop;
    p->ended = 1;
    if (!p->have_t0) return;
    j_stop = tbi_steps_ceil((p->prev_t - p->t0) / macro) * p->per_step;
    while ((p->j < j_stop && !p->pending_snap) || p->pending_snap) {
        tb_real t_far = p->t0 + (tb_real)(p->j + 1) * (macro / (tb_real)p->per_step) + macro;
        if (p->pending_snap) {
            tb_real t_b = p->t0 + (tb_real)p->k * macro;
            phys_snapshot(m, p, t_b, phys_ambient_rise(m, p, t_b, p->prev_amb));
            p->pending_snap = 0;
            continue;
        }
        /* past the log: every value held (prev sample repeated) */
        phys_fine(m, p, t_far, p->prev_x, p->prev_f, p->prev_load, p->prev_amb, j_stop);
        p->prev_t = t_far; /* interpolation between equal values is the held value */
    }
}

static int predict(const tb_model *m, const void *ks, tb_real t, tb_real axis_mm, tb_real *thermal)
{
    const tbi_phys *p = (const tbi_phys *)ks;
    int a, b;
    tb_real w;
    tb_real pf = PP(m, P_PF), sign = pf <= 0 ? 1 : -1, L = PP(m, P_L), dx = PP(m, P_DX);
    tb_real x, nodes, f, tem, dta, tea, off;
    tbi_int mi;
    const tb_real *ua, *ub;
    uint32_t n = p->n;
    if (p->n_snap == 0) return TB_E_NOTREADY;
    b = p->snap_cur;
    a = p->n_snap == 2 ? 1 - b : b;
    if (p->n_snap == 2 && t < p->snap_t[a]) return TB_E_LATE;
    w = (p->n_snap == 2 && p->snap_t[b] > p->snap_t[a]) ? (t - p->snap_t[a]) / (p->snap_t[b] - p->snap_t[a]) : 1;
    if (w < 0) w = 0;
    /* up to the newest boundary: the table interpolated in time (thermbench's model). Past it, before
     * the next boundary exists (a live compensator asking for its own time): extrapolated from the
     * last two, at most one step on; once the log has ended, held as thermbench holds it */
    if (w > (p->ended ? 1 : 2)) w = p->ended ? 1 : 2;
    x = sign * (axis_mm / (tb_real)1000 - pf);
    if (x < 0) x = 0;
    if (x > L) x = L;
    nodes = x / dx;
    mi = tbi_floor_clamp(nodes, 0, (tbi_int)n - 1);
    if (mi < 0) mi = 0;
    if (mi > (tbi_int)n - 1) mi = (tbi_int)n - 1;
    f = nodes - (tb_real)mi;
    ua = p->snap_u + (size_t)a * (n + 1);
    ub = p->snap_u + (size_t)b * (n + 1);
    tem = (ua[mi] * (1 - f) + ua[mi + 1] * f) * (1 - w) + (ub[mi] * (1 - f) + ub[mi + 1] * f) * w;
    dta = p->snap_amb[a] * (1 - w) + p->snap_amb[b] * w;
    tea = PP(m, P_ALPHA) * dta * axis_mm * (tb_real)1e-3 * (tb_real)1e6;
    off = p->snap_off[a] * (1 - w) + p->snap_off[b] * w;
    *thermal = sign * (tem + tea) + off;
    return TB_OK;
}

static tb_real ready_s(const tb_model *m, const void *ks, tb_real *horizon_s)
{
    const tbi_phys *p = (const tbi_phys *)ks;
    if (horizon_s) *horizon_s = PP(m, P_MACRO) + TB_MAX_GAP_S;
    return p->n_snap ? p->snap_t[p->snap_cur] : TBI_NO_TIME;
}

const tbi_kind tbi_kind_physics = {
    .kind = TB_KIND_PHYSICS, .max_version = 2, .pipeline = 1, .parse = parse, .carve = carve, .sample = sample,
    .finish = finish, .ready_s = ready_s, .predict = predict,
};
