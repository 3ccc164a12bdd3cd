/*
 * tb_kind_classifier.c - kind CLASSIFIER: seed 002 §2.4 eq. 15-19, the proximity naive Bayes
 * that names the working condition from the axis motion of a window (stroke, position, feed),
 * classified on a grid of step_s; a bank (tb_bank.c) switches its member models with it.
 * It takes raw samples (no sensor pipeline, no geometric block).
 * dims [K, nA, nB, nC]; body: window_s, step_s (>= the period), min_moving_s; O_A levels
 * A[nA] (stroke), B[nB] (start + end), C[nC] (feed), each increasing; O_B per condition its
 * three level indices.
 */
#include "tb_internal.h"

typedef struct {
    uint32_t cap, n, head; /* ring of samples: t (float, relative), x, f (<0: not moving) */
    uint32_t oldest;       /* its oldest slot */
    float *rt, *rx, *rf;
    tb_real t0;
    int have_t0;
    tbi_count g_next;      /* next grid index to classify */
    tb_real last_t, period;
    int have_prev;
    /* labels of the last grid points (held) */
    tb_real lab_t[4];
    int32_t lab[4];
    uint32_t lab_n, lab_head;
    int32_t held;
    float *scratch;        /* 2 x TB_MAX_FEEDS: distinct feeds of the window and their levels */
    int8_t *lvl;           /* cap: the feed level of each sample of the window being classified (-1: not moving) */
    /* the distinct moving feeds in the ring, increasing, with how many samples have each (kept as
     * samples come and go: a window's feeds without a pass over it); ftr[slot] = 1 when the slot's
     * feed is counted there, untracked the samples that did not fit the table (then: a pass) */
    float *fv;
    uint16_t *fc;
    uint8_t *ftr;
    uint32_t nfv, untracked;
} clf_t;

static void parse(tbi_cur *c, tb_model *m, uint16_t version)
{
    uint32_t *d = m->dims, i;
    uint32_t K = d[0], nA = d[1], nB = d[2], nC = d[3], k;
    (void)version;
    if (K < 1 || K > TB_MAX_CONDITIONS || nA < 1 || nA > TB_MAX_LEVELS || nB < 1 || nB > TB_MAX_LEVELS ||
        nC < 1 || nC > TB_MAX_LEVELS) {
        c->err = TB_E_DIMS;
        return;
    }
    if (!(PV(m, 0) > 0)) { c->err = TB_E_PAYLOAD; return; }
    m->off[O_BODY] = c->pos;
    tbi_take_val(c, 0, 1e6f, 1);     /* window_s */
    tbi_take_val(c, 1e-3f, 1e6f, 0); /* step_s */
    if (!c->err && PV(m, m->off[O_BODY] + 1) < PV(m, 0)) c->err = TB_E_PAYLOAD; /* step >= the period */
    tbi_take_val(c, 0, 1e6f, 0); /* min_moving_s */
    if (!c->err && PV(m, m->off[O_BODY]) / PV(m, 0) > (tb_real)TB_MAX_WINDOW) c->err = TB_E_DIMS;
    m->off[O_A] = tbi_take(c, nA + nB + nC);
    for (i = 0; i < nA + nB + nC && !c->err; i++) {
        uint32_t first = i == 0 || i == nA || i == nA + nB;
        if (!first && !(PV(m, m->off[O_A] + i) > PV(m, m->off[O_A] + i - 1))) c->err = TB_E_PAYLOAD;
    }
    m->off[O_B] = c->pos;
    for (k = 0; k < K && !c->err; k++) {
        tbi_take_int(c, 0, nA - 1);
        tbi_take_int(c, 0, nB - 1);
        tbi_take_int(c, 0, nC - 1);
    }
    m->n_sensors = 0;
}

static void carve(const tb_model *m, tbi_arena *a, void **ks)
{
    clf_t *k = (clf_t *)tbi_carve(a, sizeof(clf_t));
    size_t cap = (size_t)tbm_ceil(PV(m, m->off[O_BODY]) / PV(m, 0) - TB_R(1e-9)) + 4u; /* the window's samples */
    float *arr = (float *)tbi_carve(a, sizeof(float) * (3u * cap + 2u * TB_MAX_FEEDS));
    int8_t *lvl = (int8_t *)tbi_carve(a, cap);
    float *fv = (float *)tbi_carve(a, sizeof(float) * TB_MAX_FEEDS);
    uint16_t *fc = (uint16_t *)tbi_carve(a, sizeof(uint16_t) * TB_MAX_FEEDS);
    uint8_t *ftr = (uint8_t *)tbi_carve(a, cap);
    if (a->p && !a->err) {
        memset(k, 0, sizeof *k);
        k->lvl = lvl;
        k->fv = fv;
        k->fc = fc;
        k->ftr = ftr;
        k->cap = (uint32_t)cap;
        k->rt = arr;
        k->rx = arr + cap;
        k->rf = arr + 2 * cap;
        k->scratch = arr + 3 * cap;
        k->held = -1;
    }
    *ks = k;
}

static void clf_levels_prob(const tb_model *m, uint32_t at, uint32_t nl, tb_real v, tb_real *p)
{
    uint32_t i;
    tb_real mx = 0, tot = 0;
    int hit = 0;
    for (i = 0; i < nl; i++)
        if (tbm_fabs(PV(m, at + i)) > mx) mx = tbm_fabs(PV(m, at + i));
    if (mx < 1) mx = 1;
    for (i = 0; i < nl; i++) {
        tb_real d = tbm_fabs(v - PV(m, at + i));
        if (d <= (tb_real)1e-9 * mx) {
            p[i] = 1;
            hit = 1;
        } else {
            p[i] = 1 / d;
        }
    }
    for (i = 0; i < nl; i++) {
        tb_real d = tbm_fabs(v - PV(m, at + i));
        if (hit) p[i] = d <= (tb_real)1e-9 * mx ? 1 : 0;
        else tot += p[i];
    }
    if (!hit && tot > 0)
        for (i = 0; i < nl; i++) p[i] /= tot;
}

/* seed 002 eq. 15-19 on one motion (stroke A, position B = start + end, feed C) */
static int32_t clf_predict_one(const tb_model *m, tb_real A, tb_real B, tb_real C)
{
    uint32_t K = m->dims[0], nA = m->dims[1], nB = m->dims[2], nC = m->dims[3], k;
    tb_real pa[TB_MAX_LEVELS], pb[TB_MAX_LEVELS], pc[TB_MAX_LEVELS], best = -1;
    int32_t arg = 0;
    clf_levels_prob(m, m->off[O_A], nA, A, pa);
    clf_levels_prob(m, m->off[O_A] + nA, nB, B, pb);
    clf_levels_prob(m, m->off[O_A] + nA + nB, nC, C, pc);
    for (k = 0; k < K; k++) {
        uint32_t at = m->off[O_B] + 3 * k;
        tb_real s = pa[(uint32_t)PV(m, at)] + pb[(uint32_t)PV(m, at + 1)] + pc[(uint32_t)PV(m, at + 2)] + (tb_real)1 / (tb_real)K;
        if (s > best) {
            best = s;
            arg = (int32_t)k;
        }
    }
    return arg;
}

/* the first j with u[j] >= f in the increasing u[0..nu) (nu if none) */
static uint32_t feed_pos(const float *u, uint32_t nu, float f)
{
    uint32_t lo = 0, hi = nu;
    while (lo < hi) {
        uint32_t mid = (lo + hi) / 2u;
        if (u[mid] < f) lo = mid + 1u;
        else hi = mid;
    }
    return lo;
}

/* -DTBI_CLF_SCAN=1: every window's feeds by a pass over it, never from the table (the tests compare) */
#ifndef TBI_CLF_SCAN
#define TBI_CLF_SCAN 0
#endif

/* the sample in ring slot r enters (+1) or leaves (-1) the ring's table of distinct moving feeds */
static void clf_feed_count(clf_t *k, uint32_t r, int d)
{
    float f = k->rf[r];
    uint32_t j, q;
    if (!(f > 0)) return;
    if (d < 0 && !k->ftr[r]) {
        k->untracked--;
        return;
    }
    j = feed_pos(k->fv, k->nfv, f);
    if (j < k->nfv && k->fv[j] == f) {
        if (d > 0) k->fc[j]++;
        else if (--k->fc[j] == 0) { /* the feed's last sample left */
            for (q = j; q + 1u < k->nfv; q++) {
                k->fv[q] = k->fv[q + 1u];
                k->fc[q] = k->fc[q + 1u];
            }
            k->nfv--;
        }
    } else if (k->nfv < TB_MAX_FEEDS) {
        for (q = k->nfv; q > j; q--) {
            k->fv[q] = k->fv[q - 1u];
            k->fc[q] = k->fc[q - 1u];
        }
        k->fv[j] = f;
        k->fc[j] = 1;
        k->nfv++;
    } else {
        k->ftr[r] = 0;
        k->untracked++;
        return;
    }
    if (d > 0) k->ftr[r] = 1;
}

/* ring index i (0 = oldest) */
#define RI(k, i) ((k)->oldest + (i) < (k)->cap ? (k)->oldest + (i) : (k)->oldest + (i) - (k)->cap)

/* the first ring position whose time is after T (n if none) */
static uint32_t clf_first_after(const clf_t *k, tb_real T)
{
    uint32_t lo = 0, hi = k->n;
    while (lo < hi) {
        uint32_t mid = (lo + hi) / 2u;
        if (k->t0 + (tb_real)k->rt[RI(k, mid)] <= T) lo = mid + 1u;
        else hi = mid;
    }
    return lo;
}

/* features of the window (T - window, T] (thermbench.models.motion_windows.window_features, with the feed
 * levels clustered over the window and its two neighbour samples); returns the raw label or -1 */
static int32_t clf_window(const tb_model *m, clf_t *k, tb_real T)
{
    uint32_t body = m->off[O_BODY], i, nlev = 0, nu = 0, lo, hi, a, b, ri, rp, cap = k->cap;
    tb_real window = PV(m, body), min_moving = PV(m, body + 2), period = k->period;
    float *u = k->scratch, *lev = k->scratch + TB_MAX_FEEDS;
    tb_real time_in[TB_MAX_FEEDS], feed_in[TB_MAX_FEEDS], xs_lo[TB_MAX_FEEDS], xs_hi[TB_MAX_FEEDS], x0, x1, total = 0;
    uint32_t dom = 0;
    if (k->n == 0) return -1;
#define NX(r) ((r) + 1u == cap ? 0u : (r) + 1u) /* the next ring slot */
    /* the samples in (T - window, T]: [lo, hi) (the ring's times increase) */
    lo = clf_first_after(k, T - window);
    hi = clf_first_after(k, T);
    if (lo >= hi) return -1;
    /* distinct moving feeds of the window and its neighbours, sorted: the ring's, less the few
     * samples of the ring outside [a, b); a pass over the window when the ring's did not fit */
    a = lo > 0 ? lo - 1 : lo;
    b = hi < k->n ? hi + 1 : hi;
    if (!k->untracked && !TBI_CLF_SCAN) {
        uint16_t cnt[TB_MAX_FEEDS];
        uint32_t j;
        memcpy(u, k->fv, sizeof(float) * k->nfv);
        memcpy(cnt, k->fc, sizeof(uint16_t) * k->nfv);
        for (i = 0; i < k->n; i = i + 1u == a ? b : i + 1u) { /* [0, a) and [b, n) */
            float f;
            if (i >= a && i < b) continue; /* a = 0: the window starts the ring */
            f = k->rf[RI(k, i)];
            if (f > 0) cnt[feed_pos(u, k->nfv, f)]--;
        }
        for (j = 0; j < k->nfv; j++)
            if (cnt[j]) u[nu++] = u[j];
    }
    for (i = a, ri = RI(k, a), rp = ri; i < b && (k->untracked || TBI_CLF_SCAN); i++, rp = ri, ri = NX(ri)) {
        float f = k->rf[ri];
        uint32_t j, q;
        if (!(f > 0) || (i > a && f == k->rf[rp])) continue; /* not moving, or the feed just seen */
        j = feed_pos(u, nu, f);
        if (j < nu && u[j] == f) continue;
        if (nu == TB_MAX_FEEDS) return -2; /* more distinct feeds than the runtime clusters */
        for (q = nu; q > j; q--) u[q] = u[q - 1];
        u[j] = f;
        nu++;
    }
    if (nu == 0) return -1;
    /* chain clustering within 1 % (thermbench.models.motion_windows._cluster_feeds): lev[j] = level of u[j] */
    {
        uint32_t j;
        lev[0] = 0;
        for (j = 1; j < nu; j++) {
            if ((tb_real)u[j] - (tb_real)u[j - 1] > (tb_real)0.01 * (tb_real)u[j]) nlev++;
            lev[j] = (float)nlev;
        }
        nlev++;
    }
    for (i = 0; i < nlev; i++) {
        time_in[i] = feed_in[i] = 0;
        xs_lo[i] = TB_R(1e30); /* |axis_mm| <= TB_MAX_AXIS_MM */
        xs_hi[i] = -TB_R(1e30);
    }
    /* one pass: each sample's level (kept: the turning points read it again); over the window, the
     * time and feed-time at each level and each level's stroke range */
    for (i = a, ri = RI(k, a), rp = ri; i < b; i++, rp = ri, ri = NX(ri)) {
        float f = k->rf[ri];
        int32_t c = !(f > 0) ? -1 : (i > a && f == k->rf[rp]) ? (int32_t)k->lvl[i - a - 1] : (int32_t)lev[feed_pos(u, nu, f)];
        tb_real w, x;
        k->lvl[i - a] = (int8_t)c;
        if (c < 0 || i < lo || i >= hi) continue; /* not moving, or a neighbour of the window */
        w = i + 1 < k->n ? (tb_real)k->rt[NX(ri)] - (tb_real)k->rt[ri] : period;
        x = (tb_real)k->rx[ri];
        if (x < xs_lo[c]) xs_lo[c] = x;
        if (x > xs_hi[c]) xs_hi[c] = x;
        time_in[c] += w;
        feed_in[c] += w * (tb_real)f;
        total += w;
    }
#define LVL(idx) ((int32_t)k->lvl[(idx) - a])
    for (i = 1; i < nlev; i++)
        if (time_in[i] > time_in[dom]) dom = i;
    if (!(total >= min_moving) || !(time_in[dom] > 0)) return -1;
    x0 = xs_lo[dom]; /* the stroke range at the dominant feed */
    x1 = xs_hi[dom];
    {
        /* turning points between samples (1 Hz aliasing), see window_features */
        tb_real up = x1, down = x0, tol = (tb_real)1e-6;
        int32_t cprev, c0, c1n, c2;
        {
            tb_real mx = 1;
            if (tbm_fabs(x0) > mx) mx = tbm_fabs(x0);
            if (tbm_fabs(x1) > mx) mx = tbm_fabs(x1);
            tol = (tb_real)1e-6 * mx;
        }
        for (i = lo, ri = RI(k, lo); i + 1 < hi; i++, ri = NX(ri)) {
            uint32_t rn = NX(ri);
            float fa;
            tb_real dt, L, gap;
            tb_real xa, xb, top, bot;
            int t_in, b_in;
            c0 = LVL(i);
            if (c0 != (int32_t)dom) continue;
            fa = k->rf[ri];
            if (i == 0) continue; /* run start (same[0] is False) or the sample before it left the ring */
            cprev = LVL(i - 1);
            c1n = LVL(i + 1);
            if (i + 2 < k->n) c2 = LVL(i + 2);
            else c2 = -100;
            if (!(cprev == c0 && c1n == c0 && c2 == c1n)) continue;
            dt = (tb_real)k->rt[rn] - (tb_real)k->rt[ri];
            if (!(dt <= TB_R(1.5) * period)) continue;
            xa = (tb_real)k->rx[ri];
            xb = (tb_real)k->rx[rn];
            L = (tb_real)fa / TB_R(60.0) * dt;
            gap = L - tbm_fabs(xb - xa);
            if (!(gap > TB_R(0.02) * L + TB_R(0.1))) continue;
            top = (xa + xb + L) / 2;
            bot = (xa + xb - L) / 2;
            t_in = top < x1 - tol;
            b_in = bot > x0 + tol;
            if (b_in && !t_in && top > up) up = top;
            if (t_in && !b_in && bot < down) down = bot;
        }
        x0 = down;
        x1 = up;
    }
#undef LVL
#undef NX
    return clf_predict_one(m, x1 - x0, x0 + x1, feed_in[dom] / time_in[dom]);
}

static void clf_label_push(clf_t *k, tb_real T, int32_t raw)
{
    if (raw >= 0) k->held = raw;
    k->lab_t[k->lab_head] = T;
    k->lab[k->lab_head] = k->held;
    k->lab_head = (k->lab_head + 1) % 4u;
    if (k->lab_n < 4) k->lab_n++;
}

static void clf_classify_due(const tb_model *m, clf_t *k, tb_real t_now, int final)
{
    tb_real step = PV(m, m->off[O_BODY] + 1);
    if (!k->have_t0) return;
    for (;;) {
        tb_real T = k->t0 + (tb_real)k->g_next * step;
        if (!final && !(T <= t_now)) break; /* a sample at T itself completes T's window (the live compensator's label at T) */
        if (final && T > k->last_t + TB_R(1e-9)) break;
        clf_label_push(k, T, clf_window(m, k, T));
        k->g_next++;
    }
}

static int step(const tb_model *m, void *ks, const tb_sample *s)
{
    clf_t *k = (clf_t *)ks;
    uint32_t at;
    if (!k->have_t0) {
        k->have_t0 = 1;
        k->t0 = s->t_s;
        k->period = PV(m, 0);
    }
    if (k->n == k->cap) { /* drop the oldest (the slot written next) */
        clf_feed_count(k, k->head, -1);
        k->n--;
    }
    at = k->head;
    k->rt[at] = (float)(s->t_s - k->t0);
    k->rx[at] = (float)s->axis_mm;
    k->rf[at] = (!s->measuring && s->feed_mm_min > 0) ? (float)s->feed_mm_min : -1.0f;
    clf_feed_count(k, at, 1);
    k->head = (k->head + 1) % k->cap;
    k->n++;
    k->oldest = (k->head + k->cap - k->n) % k->cap;
    k->last_t = s->t_s;
    /* grid points up to this sample can be classified now (their window is in: a grid point between
     * two samples needs the later one, a grid point at this sample only this one) */
    clf_classify_due(m, k, s->t_s, 0);
    return TB_OK;
}

static tb_real clf_ready(const tb_model *m, const clf_t *k)
{
    if (!k->have_t0) return TBI_NO_TIME;
    return TBI_BEFORE(k->t0 + (tb_real)k->g_next * PV(m, m->off[O_BODY] + 1)); /* the label at that grid time needs the sample at it (or a later one) */
}

static tb_real clf_horizon(const tb_model *m) { return PV(m, m->off[O_BODY] + 1) + TB_MAX_GAP_S; }

static tb_real ready_s(const tb_model *m, const void *ks, tb_real *horizon_s)
{
    if (horizon_s) *horizon_s = clf_horizon(m);
    return clf_ready(m, (const clf_t *)ks);
}

int tb_classifier_label_at(const tb_model *clf, tb_real t_s, int32_t *label)
{
    const clf_t *k;
    uint32_t i;
    int32_t out = -1;
    tb_real best = TBI_NO_TIME;
    if (!clf || !clf->state || clf->kind != TB_KIND_CLASSIFIER || !label) return TB_E_STATE;
    k = (const clf_t *)((const tbi_state *)clf->state)->ks;
    if (k->have_t0 && t_s > clf_ready(clf, k) + clf_horizon(clf)) return TB_E_NOTREADY;
    if (k->lab_n == 0) {
        *label = -1;
        return k->have_t0 ? TB_OK : TB_E_NOTREADY;
    }
    for (i = 0; i < k->lab_n; i++) {
        uint32_t at = (k->lab_head + 4u - 1u - i) % 4u;
        if (k->lab_t[at] <= t_s + TB_R(1e-9) && k->lab_t[at] > best) {
            best = k->lab_t[at];
            out = k->lab[at];
        }
    }
    if (best == TBI_NO_TIME) {
        uint32_t oldest = (k->lab_head + 4u - k->lab_n) % 4u;
        if (k->lab_n == 4) return TB_E_LATE;
        out = t_s < k->lab_t[oldest] ? -1 : k->lab[oldest];
    }
    *label = out;
    return TB_OK;
}

static int check(const tb_model *m, const void *ks, const tb_sample *s)
{
    const clf_t *k = (const clf_t *)ks;
    (void)m;
    if (k->have_t0 && !(s->t_s > k->last_t)) return TB_E_INPUT;
    if (k->have_t0 && s->t_s - k->last_t > TB_MAX_GAP_S) return TB_E_SAMPLING;
    return TB_OK;
}

static void finish(const tb_model *m, void *ks) { clf_classify_due(m, (clf_t *)ks, 0, 1); }

int tbi_classifier_span(const tb_model *clf, tb_real *t_first, tb_real *t_last)
{
    const clf_t *k = (const clf_t *)((const tbi_state *)clf->state)->ks;
    *t_first = k->t0;
    *t_last = k->last_t;
    return k->have_t0;
}

const tbi_kind tbi_kind_classifier = {
    .kind = TB_KIND_CLASSIFIER, .max_version = 1, .pipeline = 0, .parse = parse, .carve = carve, .check = check,
    .step = step, .finish = finish, .ready_s = ready_s,
};
