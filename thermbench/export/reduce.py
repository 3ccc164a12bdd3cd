"""Reduced-set LSSVM export: fewer kernel centres for the embedded compensator.

An LSSVM is not sparse: every training reading is a support vector (seed 002
eq. 13-14), so the file grows with the data and each prediction costs one kernel
evaluation per reading; seed 002 deploys MLR on its STM32F407 for that reason.
The reduced set replaces the N support vectors by m << N centres (k-means of the
standardised training inputs, :class:`sklearn.cluster.KMeans` with a seed) and
re-solves the weights and bias by least squares so that the small expansion
reproduces the full model's output at every training input (the classic
reduced-set idea, Burges 1996, with fixed centres).
"""

from __future__ import annotations

import copy

import numpy as np
from sklearn.cluster import KMeans
from threadpoolctl import threadpool_limits

from ..models.lssvm import PSOLSSVM, rbf_kernel
from .encoding import ExportError


def reduced_lssvm(model: PSOLSSVM, size: int, seed: int = 0) -> PSOLSSVM:
    """A copy of the fitted ``model`` whose regressor has ``size`` centres (``size`` >= N
    returns an unchanged copy). ``n_support_`` and ``memory_bytes_`` follow the new size;
    ``reduced_from_`` records N."""
    if isinstance(size, bool) or not isinstance(size, (int, np.integer)) or size < 1:
        raise ExportError(f"export.lssvm_reduced_size must be an integer >= 1, got {size!r}")
    r = model.regressor_
    X = np.asarray(r.X_fit_, dtype=float)
    out = copy.deepcopy(model)
    out.reduced_from_ = int(X.shape[0])
    if size >= X.shape[0]:
        return out
    # one thread: k-means and the solve give the same bits however many cores or processes run them
    with threadpool_limits(1):
        km = KMeans(n_clusters=int(size), random_state=int(seed), n_init=4).fit(X)
        centres = km.cluster_centers_
        target = rbf_kernel(X, X, r.sigma2_) @ r.alpha_ + r.b_
        A = np.column_stack([rbf_kernel(X, centres, r.sigma2_), np.ones(X.shape[0])])
        scale = np.max(np.abs(A), axis=0)
        scale[scale == 0] = 1.0
        sol, *_ = np.linalg.lstsq(A / scale, target, rcond=1e-12)
        sol = sol / scale
    reg = out.regressor_
    reg.X_fit_, reg.alpha_, reg.b_ = centres, sol[:-1], float(sol[-1])
    reg.n_support_ = int(size)
    reg.memory_bytes_ = 8 * (size * X.shape[1] + size + 2 + 2 * X.shape[1])
    out.n_support_, out.memory_bytes_ = reg.n_support_, reg.memory_bytes_
    return out
