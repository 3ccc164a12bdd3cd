"""The test that names the missing effect, and the numbers it reads.

The test (:class:`SignificanceTest`): a candidate is *significant* when the systematic
error it explains on held-out runs, sqrt(RMSE_before^2 - RMSE_after^2), is at
least ``explained_x_floor`` times the noise floor and its BIC gain exceeds
``bic_min`` (10: "very strong" evidence, Kass & Raftery 1995). The best
significant candidate (lowest held-out RMSE) is named; another significant one
*ties* with it when what the best explains beyond it, sqrt(RMSE_other^2 -
RMSE_best^2), is below ``tie_x_floor`` times the floor and the best's BIC gain
does not exceed the other's by more than ``bic_min``: the data cannot tell them
apart, and both names are reported instead of a guess. The named effect
is added only when its proper leave-one-run-out score passes the same test.

BIC = n ln(SSE/n) + p ln n (Schwarz 1978) (:func:`bic`); the systematic error a candidate
explains (:func:`explained`); a candidate's name with its signal (:func:`display`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class SignificanceTest:
    explained_x_floor: float = 2.0
    bic_min: float = 10.0
    tie_x_floor: float = 1.0
    within_x_floor: float = 1.5

    def describe(self) -> str:
        return (
            f"named when the held-out error it explains, sqrt(RMSE_before^2 - RMSE_after^2), is >= "
            f"{self.explained_x_floor:g} x the noise floor and its BIC gain is > {self.bic_min:g}; "
            f"two significant candidates tie when the better explains < {self.tie_x_floor:g} x the noise "
            f"floor beyond the other and its BIC gain is not > {self.bic_min:g} above the other's; a model explains the data (verdict none or found) only when its held-out "
            f"RMSE is <= {self.within_x_floor:g} x the noise floor"
        )

    def within_floor(self, heldout_um: float, floor_um: float) -> bool:
        """Whether a held-out RMSE is within the noise floor by this test."""
        return bool(heldout_um <= self.within_x_floor * floor_um)


def bic(sse: float, n: int, p: int) -> float:
    return float(n * np.log(max(sse, 1e-300) / n) + p * np.log(n))


def explained(before_um: float, after_um: float) -> float:
    return float(np.sqrt(max(0.0, before_um**2 - after_um**2)))


def decide(cands: list[dict], floor_um: float, test: SignificanceTest) -> tuple[dict | None, list[str]]:
    """The best significant candidate and the candidates it ties with.

    Another significant candidate ties with the best when the best explains less than
    ``tie_x_floor`` x the floor beyond it on held-out runs and does not beat its BIC gain by
    more than ``bic_min``: neither half of the test tells them apart.

    Candidates whose identified forms are the same physics (the same ``label``: an open term
    within tolerance of a canonical effect) do not tie: of the significant ones with the best's
    label, the one with the fewest parameters is named. The same open term on other signals does not tie either: its form is named, and the
    signals that drive it alike are listed (``alike``). Distinct physics within
    ``tie_x_floor`` of the best tie."""
    sig = sorted((c for c in cands if c.get("significant")), key=lambda c: c["heldout_rmse_um"])
    if not sig:
        return None, []
    best = sig[0]
    # within the tie band by held-out error, unless the best's BIC gain beats the other's by more
    # than bic_min: then the data tell them apart by the test's other half
    band = [c for c in sig[1:] if explained(c["heldout_rmse_um"], best["heldout_rmse_um"]) < test.tie_x_floor * floor_um
            and not best.get("bic_gain", 0.0) - c.get("bic_gain", 0.0) > test.bic_min]  # fmt: skip
    # the same physics (one label): the fewest parameters, wherever it scored among the significant
    # (a canonical effect whose fit scored worse than the open term that is it is an optimiser's miss,
    # and the constrained form extrapolates to an unseen run's feed better)
    pick = min([c for c in sig if c["label"] == best["label"]], key=lambda c: (c["n_params"], c["heldout_rmse_um"]))
    # the same open term on another signal: the form is found, its driver is not told apart
    pick = {**pick, "alike": [display(c) for c in band if c["label"] != best["label"] and c["effect"] == pick["effect"]]}
    ties = [display(c) for c in band if c["label"] != best["label"] and c["effect"] != pick["effect"]]
    return pick, ties


def display(c: dict) -> str:
    """A candidate's name with its signal: ``driven_offset[T_bed]``."""
    return c["effect"] + (f"[{next(iter(c['variant'].values()))}]" if c.get("variant") else "")
