"""Numerical kernels of the seed 000 finite-difference ball-screw model (numba).

Two integrators of the same semi-discrete model (seed 000 §3.1):

* :func:`explicit_run` is the paper's iteration literally: forward Euler with the
  fine step ``dt`` (0.1 s in seed 000 Table 1). It is the reference.
* :func:`macro_run` integrates the same semi-discrete system with large steps
  (e.g. 10 s): within each macro step the heat inputs and convective
  conductances of every node are replaced by their exact average over the fine
  samples of that step (so the energy entering the screw is the same as in the
  explicit scheme), and the resulting linear system is advanced by the
  L-stable, second-order SDIRK2 method (Alexander 1977), two tridiagonal solves
  per step. Benchmarked against the explicit scheme in ``benchmarks/``.

Node classification per fine sample follows the seed 000 §3.1 piecewise
update: node n = 1 and 1 < n <= LB/dx are fixed-bearing nodes (bearing heat
QB/LB per length, no convection); nodes under the nut get QN/LN per length
and no convection (edge nodes in proportion to the covered fraction, see
:func:`_nut_cover`); node N convects over its cylinder and its end face,
factor (1 + D/(4 dx)); every other node convects over its cylinder. Nodes are
0-based here (index i = n - 1).

Seed 001 §4 (eq. 3-9) is a second statement of the same physics: per segment
c m dT = Q_friction - Q_conduction - Q_convection, T(t + dt) = T(t) + dT, and
the elongation sum alpha (T_i - T_f) L_i (eq. 9) is seed 000 §3.2's integral.

All temperatures are rises ``theta = T - Ta0`` above the initial ambient.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def _nut_cover(x_nut_m, half_len_m, dx_m, n_bearing, n_nodes):
    """Nodes under the nut and the covered fraction of the two edge nodes.

    Node i (0-based) spans [i dx, (i + 1) dx]. The nut spans [XN - LN/2, XN + LN/2]
    (seed 000 §3.1), after the fixed-bearing nodes, which come first in the
    piecewise update. Returns (lo, hi, w_lo, w_hi): nodes lo..hi inclusive are
    covered, fully except the edge nodes, covered by w_lo and w_hi; lo > hi when
    the nut covers nothing. Seed 000 counts a node as covered when its right face
    lies under the nut; the fractional edges are that rule's consistent form: the
    nut's power stays exactly QN at every position and the heat input varies
    continuously with XN, so the scheme converges in dx and dt even when the nut
    travels more than dx per step (9000 mm/min at dt = 0.1 s is 15 mm).
    """
    a = x_nut_m - half_len_m
    b = x_nut_m + half_len_m
    a_min = n_bearing * dx_m
    if a < a_min:
        a = a_min
    l_m = n_nodes * dx_m
    if b > l_m:
        b = l_m
    if b <= a:
        return 1, 0, 0.0, 0.0
    lo = int(np.floor(a / dx_m))
    hi = int(np.floor(b / dx_m))
    if hi >= n_nodes:
        hi = n_nodes - 1
    if lo == hi:
        w = (b - a) / dx_m
        return lo, hi, w, w
    return lo, hi, (lo + 1) - a / dx_m, b / dx_m - hi


@njit(cache=True)
def _add_cover(d, k, lo, hi, w_lo, w_hi, value):
    """Add ``value`` x coverage to row k of the difference array d."""
    d[k, lo] += value
    d[k, hi + 1] -= value
    d[k, lo] -= value * (1.0 - w_lo)
    d[k, lo + 1] += value * (1.0 - w_lo)
    if hi != lo:
        d[k, hi] -= value * (1.0 - w_hi)
        d[k, hi + 1] += value * (1.0 - w_hi)


@njit(cache=True)
def accumulate_cover(x_nut_m, weights, n_per_step, n_steps, n_nodes, dx_m, half_nut_m, n_bearing):
    """Average over each macro step of the nut's coverage of every node, plain and weighted.

    ``weights`` (n_w, n_fine): per fine sample series w (e.g. the speed). Returns
    ``out`` of shape (n_w + 1, n_steps, n_nodes): ``out[0]`` the mean covered
    fraction of each node, ``out[1 + s]`` the mean of ``weights[s] x`` covered fraction.
    The step averages of anything affine in such series follow without another pass
    over the fine samples: with h = k1 v + k2 the mean of h x covered fraction is
    ``k1 out[v] + k2 out[0]`` (the heat parameterisation of seed 000 §4.1).
    """
    n_w = weights.shape[0]
    d = np.zeros((n_w + 1, n_steps, n_nodes + 1))
    for j in range(n_steps * n_per_step):
        k = j // n_per_step
        lo, hi, w_lo, w_hi = _nut_cover(x_nut_m[j], half_nut_m, dx_m, n_bearing, n_nodes)
        if hi >= lo:
            _add_cover(d[0], k, lo, hi, w_lo, w_hi, 1.0)
            for s in range(n_w):
                _add_cover(d[s + 1], k, lo, hi, w_lo, w_hi, weights[s, j])
    out = np.empty((n_w + 1, n_steps, n_nodes))
    inv = 1.0 / n_per_step
    for s in range(n_w + 1):
        for k in range(n_steps):
            a = 0.0
            for i in range(n_nodes):
                a += d[s, k, i]
                out[s, k, i] = a * inv
    return out


@njit(cache=True)
def macro_run(theta0, q_W, g_W_K, dta_C, dt_s, cap_J_K, cond_W_K, energy=True):
    """Advance the semi-discrete model over macro steps with SDIRK2, for one or several
    heat inputs that share the conductances.

    Node equation: ``cap * dtheta_i/dt = cond*(theta_{i+1} - 2 theta_i + theta_{i-1})
    + q_i - g_i * (theta_i - dTa)`` with adiabatic left end and no conduction
    beyond the right end (seed 000 §3.1). ``q_W`` (n_rhs, n_steps, n_nodes) the step-average
    heat inputs of ``n_rhs`` runs (each with its ``theta0`` row, (n_rhs, n_nodes)), ``g_W_K``
    (n_steps, n_nodes) their common step-average convective conductances, ``dta_C`` the mean
    ambient change per step. The runs share each step's matrix: it is factorised once per
    step (the Thomas algorithm's pivots), so a further run costs the substitutions only,
    with the same arithmetic as alone (identification's basis runs, variable projection).

    Returns the states at the step boundaries, shape (n_rhs, n_steps + 1, n_nodes),
    and the convected heat per step (J), (n_rhs, n_steps), consistent with the scheme
    (``energy`` False: not accumulated, shape (n_rhs, 0); the states are the same).
    """
    n_rhs, n_steps, n = q_W.shape
    gamma = 1.0 - np.sqrt(2.0) / 2.0
    out = np.empty((n_rhs, n_steps + 1, n))
    conv_J = np.empty((n_rhs, n_steps if energy else 0))
    # node-major work arrays: the runs' independent substitutions interleave (one chain per run)
    y = np.empty((n, n_rhs))
    for r in range(n_rhs):
        for i in range(n):
            out[r, 0, i] = theta0[r, i]
            y[i, r] = theta0[r, i]
    ipiv = np.empty(n)  # the reciprocal Thomas pivots: the substitutions multiply
    cp = np.empty(n)
    src = np.empty((n, n_rhs))
    y1 = np.empty((n, n_rhs))
    y2 = np.empty((n, n_rhs))
    e = np.empty(n_rhs)
    gh = gamma * dt_s
    off = -gh * cond_W_K
    c1 = (1.0 - gamma) / gamma
    for k in range(n_steps):
        ta = dta_C[k]
        # the step's matrix (diagonal cap + gh (cond stencil + g), off-diagonal -gh cond), factorised
        prev = 0.0
        for i in range(n):
            nb = 2.0
            if i == 0 or i == n - 1:
                nb = 1.0
            ip = 1.0 / (cap_J_K + gh * (nb * cond_W_K + g_W_K[k, i]) - off * prev)
            ipiv[i] = ip
            prev = off * ip
            cp[i] = prev
        # first stage (cap + gh A) Y1 = cap y + gh s: the right-hand side made within the forward sweep
        for i in range(n):
            ip = ipiv[i]
            gt = g_W_K[k, i] * ta
            for r in range(n_rhs):
                s = gh * (q_W[r, k, i] + gt)
                src[i, r] = s
                a = 0.0 if i == 0 else y1[i - 1, r]
                y1[i, r] = (cap_J_K * y[i, r] + s - off * a) * ip
        _back(cp, y1)
        # f1 = (Y1 - y)/(gamma h): second stage y + (1-gamma) h f1 + gamma h f(Y2)
        for i in range(n):
            ip = ipiv[i]
            for r in range(n_rhs):
                a = 0.0 if i == 0 else y2[i - 1, r]
                y2[i, r] = (cap_J_K * (y[i, r] + c1 * (y1[i, r] - y[i, r])) + src[i, r] - off * a) * ip
        _back(cp, y2)
        if energy:
            e[:] = 0.0
            for i in range(n):
                for r in range(n_rhs):
                    e[r] += g_W_K[k, i] * ((1.0 - gamma) * (y1[i, r] - ta) + gamma * (y2[i, r] - ta))
            for r in range(n_rhs):
                conv_J[r, k] = e[r] * dt_s
        for i in range(n):
            for r in range(n_rhs):
                y[i, r] = y2[i, r]
                out[r, k + 1, i] = y2[i, r]
    return out, conv_J


@njit(cache=True)
def _back(cp, x):
    """The back substitution of the Thomas algorithm (``cp = off / pivot``), in place, for
    each column of ``x`` (n_nodes, n_rhs): the forward sweep is fused with the right-hand
    side in :func:`macro_run`."""
    n, n_rhs = x.shape
    for i in range(n - 2, -1, -1):
        for r in range(n_rhs):
            x[i, r] -= cp[i] * x[i + 1, r]


@njit(cache=True)
def explicit_run(
    theta0,
    x_nut_m,
    qn_W,
    qb_W,
    h_W_m2K,
    dta_C,
    src_weights,
    src_power_W,
    dt_s,
    n_per_out,
    dx_m,
    half_nut_m,
    nut_len_m,
    n_bearing,
    bearing_len_m,
    cap_J_K,
    cond_W_K,
    side_area_m2,
    end_area_m2,
):
    """The seed 000 §3.1 iteration, literally (forward Euler at the fine step).

    Returns the states every ``n_per_out`` fine steps, shape (n_out + 1, n_nodes).
    """
    n = theta0.shape[0]
    n_fine = x_nut_m.shape[0]
    n_out = n_fine // n_per_out
    out = np.empty((n_out + 1, n))
    out[0, :] = theta0
    y = theta0.copy()
    new = np.empty(n)
    n_src = src_weights.shape[0]
    per_node_b = dx_m / bearing_len_m if bearing_len_m > 0 else 0.0
    per_node_n = dx_m / nut_len_m
    for j in range(n_out * n_per_out):
        lo, hi, w_lo, w_hi = _nut_cover(x_nut_m[j], half_nut_m, dx_m, n_bearing, n)
        h = h_W_m2K[j]
        ta = dta_C[j]
        for i in range(n):
            if n == 1:
                lap = 0.0
            elif i == 0:
                lap = y[1] - y[0]
            elif i == n - 1:
                lap = y[n - 2] - y[n - 1]
            else:
                lap = y[i + 1] + y[i - 1] - 2.0 * y[i]
            p = cond_W_K * lap
            if i < n_bearing:
                p += qb_W[j] * per_node_b
            else:
                w = 0.0
                if lo <= i <= hi:
                    w = 1.0
                    if i == lo:
                        w = w_lo
                    elif i == hi:
                        w = w_hi
                p += w * qn_W[j] * per_node_n
                area = side_area_m2 + (end_area_m2 if i == n - 1 else 0.0)
                p -= (1.0 - w) * h * area * (y[i] - ta)
            for s in range(n_src):
                p += src_weights[s, i] * src_power_W[s, j]
            new[i] = y[i] + dt_s * p / cap_J_K
        for i in range(n):
            y[i] = new[i]
        if (j + 1) % n_per_out == 0:
            out[(j + 1) // n_per_out, :] = y
    return out


@njit(cache=True)
def read_node_sums(theta, rows, rk, rk1, m, f, w):
    """Per reading r, the field's node sum up to face m_r + f_r (sum_{i<m} theta_i + f theta_m,
    seed 000 §3.2's elongation integral without its alpha dx and ambient) at steps ``rows[rk_r]``
    and ``rows[rk1_r]``, interpolated with weight ``w_r`` towards the second. The cumulative sums
    are made for the listed ``rows`` only."""
    n_nodes = theta.shape[1]
    c = np.empty((rows.size, n_nodes + 1))
    for a in range(rows.size):
        row = rows[a]
        s = 0.0
        c[a, 0] = 0.0
        for i in range(n_nodes):
            s += theta[row, i]
            c[a, i + 1] = s
    out = np.empty(rk.size)
    for r in range(rk.size):
        j = m[r]
        fr = f[r]
        at_k = c[rk[r], j] * (1.0 - fr) + c[rk[r], j + 1] * fr
        at_k1 = c[rk1[r], j] * (1.0 - fr) + c[rk1[r], j + 1] * fr
        out[r] = at_k * (1.0 - w[r]) + at_k1 * w[r]
    return out
