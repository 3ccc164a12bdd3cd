"""Gauss-Newton steps within a box: the polish that takes the coarse stage's optimum of
:class:`~thermbench.models.physics.PhysicsModel` to the model's own (module docstring there,
"Coarse to fine")."""

from __future__ import annotations

import numpy as np
from scipy.optimize import lsq_linear

__all__ = ["gauss_newton"]


def gauss_newton(fun, z: np.ndarray, box: tuple[np.ndarray, np.ndarray], steps: int,
                 jac: np.ndarray | None = None) -> tuple[np.ndarray, int]:
    """Up to ``steps`` Gauss-Newton steps on the residual ``fun`` from ``z`` within ``box``: a
    forward-difference Jacobian (relative step 1e-5, as scipy's), the step by bounded linear
    least squares, halved up to three times until the squared residual falls; a step that never
    lowers it ends the search. ``jac``: a Jacobian at ``z`` to take the first step with instead
    (the coarse stage's, of a residual that differs from ``fun`` only by its time steps: a
    simplified Gauss-Newton step: the Jacobian of a nearby problem); if that step does not lower the residual,
    it is taken again with the forward-difference Jacobian. Returns the point and the steps taken."""
    lo, hi = box
    if jac is not None and jac.shape[1] != z.size:
        raise ValueError(f"gauss_newton: jac has {jac.shape[1]} columns, expected {z.size}")
    r = fun(z)
    if jac is not None and jac.shape[0] != r.size:
        raise ValueError(f"gauss_newton: jac has {jac.shape[0]} rows, expected {r.size} (the residual's size)")
    taken = 0
    while taken < steps:
        borrowed = jac is not None
        jac = jac if borrowed else _forward_jacobian(fun, z, r, box)
        step = lsq_linear(jac, -r, bounds=(lo - z, hi - z), method="bvls").x
        jac = None
        for _ in range(4):
            zn = np.clip(z + step, lo, hi)
            rn = fun(zn)
            if rn @ rn < r @ r:
                break
            step = step / 2.0
        else:
            if borrowed:
                continue  # again with the model's own Jacobian
            return z, taken
        z, r, taken = zn, rn, taken + 1
    return z, taken


def _forward_jacobian(fun, z: np.ndarray, r: np.ndarray, box) -> np.ndarray:
    """The forward-difference Jacobian of ``fun`` at ``z`` (``r = fun(z)``), each step turned
    back into ``box`` where it would leave it."""
    lo, hi = box
    jac = np.empty((r.size, z.size))
    for j in range(z.size):
        h = 1e-5 * max(1.0, abs(z[j])) * (1.0 if z[j] >= 0 else -1.0)
        if not lo[j] <= z[j] + h <= hi[j]:
            h = -h
        zh = z.copy()
        zh[j] += h
        jac[:, j] = (fun(zh) - r) / h
    return jac
