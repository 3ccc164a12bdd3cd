/*
 * tb_physics.h - the physics kind (tb_kind_physics.c) and its effects (tb_fx_<name>.c):
 * the state they share and the table every effect fills (docs/extending.md, "The C side").
 *
 * An effect is the C half of a thermbench.sim.effects.Effect class with an export_code: a
 * section (code, n_params, params...) of the physics payload (v2), read by the effect's own
 * functions. Its hooks mirror the Python ones; each is optional (0: no change).
 */
#ifndef TB_PHYSICS_H
#define TB_PHYSICS_H

#include "tb_internal.h"

#define TBI_MAX_EFFECTS 8u      /* effect sections in one payload */
#define TBI_MAX_EFFECT_CODE 63u /* section codes 1..63 */

/* the core parameters the hot loops use, decoded once per call (payload reads cannot be hoisted
 * by the compiler: the payload is bytes, which may alias the state) */
typedef struct {
    uint32_t n, nb;    /* slices; fixed-bearing slices */
    tb_real dt, macro; /* fine step, macro step (s) */
    tb_real dx, half, L, pf, sign, per_node, k1, k2, k3, k4;
    tb_real cap, cond, side, end, bear_len;
} tbi_phys_par;

typedef struct tbi_effect tbi_effect;

typedef struct {
    const tbi_effect *fx; /* its table */
    void *self;           /* its decoded parameters and running state (fx->self_bytes, in the arena) */
} tbi_fx;

/* the running state of a physics model */
typedef struct {
    uint32_t n, per_step;
    int have_t0, pending_snap, ended; /* ended: tb_model_finish ran (the log's end is known) */
    tb_real t0, prev_t;
    tb_real prev_x, prev_f, prev_load, prev_amb; /* previous sample (filtered ambient rise) */
    tbi_count j; /* next fine step */
    tbi_count k; /* macro steps done */
    tb_real *theta, *q_nut, *h_cov, *diag, *rhs, *y1, *y2, *cp;
    tb_real h_sum, qb_sum, dta_sum, v_sum; /* sums over the fine steps of the macro step */
    /* snapshots of the compensation table (seed 000 §4.3) at the last two step boundaries */
    int n_snap;
    tb_real snap_t[2];
    tb_real snap_amb[2], snap_off[2];
    tb_real *snap_u; /* 2 x (n + 1) */
    int snap_cur;
    tb_real amb_b_start; /* ambient rise at the step start */
    /* the effects, in code order; the ones with a per-fine-step hook listed again */
    tbi_fx *fx;
    const tbi_fx *amb; /* the one with an ambient (0: none, or a measured ambient) */
    uint8_t n_fx, n_nut, n_fine, nut[TBI_MAX_EFFECTS], fine[TBI_MAX_EFFECTS];
} tbi_phys;

/* One effect (tbi_effect_<name> in tb_fx_<name>.c, listed in tb_registry.def). The hooks are
 * called in increasing code order when several effects have them. */
struct tbi_effect {
    uint32_t code;       /* its section code: export_code of its Python class */
    uint32_t n_params;   /* parameters in its section (the file must say the same) */
    uint32_t self_bytes; /* decoded parameters + running state, placed (zeroed) in the arena */
    /* at open: are the parameters at payload index `at` in their domains? TB_OK or TB_E_PAYLOAD */
    int (*validate)(const tb_model *m, uint32_t at);
    /* at start: decode the parameters into self */
    void (*init)(void *self, const tb_model *m, uint32_t at, const tbi_phys_par *c);
    /* the ambient's rise tt s after the first sample, when no ambient sensor is read
     * (Effect.ambient_C; the first effect with it is used) */
    tb_real (*ambient_rise)(const void *self, tb_real tt);
    /* per fine step, for a run of count consecutive fine steps of one macro step (in time order):
     * v[i] >= 0 the speed (mm/min), load[i] the axial load (N) */
    void (*nut_heat)(const void *self, const tb_real *v, const tb_real *load, tb_real *qn, uint32_t count);
                                                              /* qn[i] += extra nut power, W (Effect.nut_heat_W) */
    void (*fine)(void *self, const tb_real *v, uint32_t count); /* accumulate a heat source over the macro step */
    /* per macro step (Effect.sources): add the step's mean source power to the slices' q[0..n-1]
     * (inv = 1 / fine steps per macro step), then start the next step's sums */
    void (*source)(void *self, tb_real *q, uint32_t n, tb_real inv);
    void (*step_start)(void *self, const tbi_phys_par *c, const tbi_phys *p); /* a macro step begins */
    /* a macro step ended (theta updated): qb_mean, v_mean its mean fixed-bearing heat and speed */
    void (*step_end)(void *self, const tbi_phys_par *c, const tbi_phys *p, tb_real qb_mean, tb_real v_mean);
    /* the read-out at a step boundary: the growth u[0..n] at the slice faces, um
     * (Effect.adjust_elongation_um), and a position-independent offset, um (Effect.offset_um) */
    void (*elongation)(const void *self, tb_real *u, uint32_t n);
    tb_real (*offset)(const void *self);
};

const tbi_effect *tbi_effect_of(uint32_t code); /* 0: no such effect */

#endif /* TB_PHYSICS_H */
