"""One motion classified against a configured condition set (seed 002 Table 6 style), as a
small text table: ``thermbench classify``."""

from __future__ import annotations

from numbers import Real

import numpy as np
import pandas as pd

from .classify import ClassifierError, ProximityNaiveBayes

__all__ = ["classify_motion", "format_classification"]


def _seed002_classifier() -> ProximityNaiveBayes:
    from hydra.utils import instantiate
    from omegaconf import OmegaConf

    from ..config import config_dir

    path = config_dir() / "classifier" / "seed002.yaml"
    return instantiate(OmegaConf.load(path), _convert_="all")


def classify_motion(stroke_mm, start_mm, end_mm, feed_mm_min, classifier=None) -> tuple[str, pd.DataFrame]:
    """Classify one motion (seed 002 Table 6 style) against the conditions of
    ``classifier`` (default: seed 002 Table 5, ``conf/classifier/seed002.yaml``).

    Returns the label and a DataFrame indexed by condition with the eq. 16
    probabilities of the condition's stroke, position and feed levels, the eq. 19
    ``score`` and ``probability`` (the score normalised to sum 1). The stroke must
    equal |end - start| within 1 mm; the feed must be >= 0.
    """
    vals = {"stroke_mm": stroke_mm, "start_mm": start_mm, "end_mm": end_mm, "feed_mm_min": feed_mm_min}
    for k, v in vals.items():
        if isinstance(v, bool) or not isinstance(v, Real) or not np.isfinite(v):
            raise ClassifierError(f"{k} must be a finite number, got {v!r}")
    if feed_mm_min < 0:
        raise ClassifierError(f"feed_mm_min must be >= 0, got {feed_mm_min}")
    if stroke_mm < 0:
        raise ClassifierError(f"stroke_mm must be >= 0, got {stroke_mm}")
    if abs(stroke_mm - abs(end_mm - start_mm)) > 1.0:
        raise ClassifierError(
            f"stroke_mm {stroke_mm:g} must equal |end_mm - start_mm| = {abs(end_mm - start_mm):g} within 1 mm"
        )
    clf = classifier if classifier is not None else _seed002_classifier()
    if getattr(clf, "factors", None) is not None:
        raise ClassifierError(f"classify_motion classifies axis motion; this classifier's factors are "
                              f"{list(clf.factors)} (classifier.factors must be null)")  # fmt: skip
    if not hasattr(clf, "classes_"):
        clf.fit()
    X = pd.DataFrame({k: [float(v)] for k, v in vals.items()})
    fp = clf.factor_probabilities(X)[0]
    scores = clf.condition_scores(X)[0]
    table = pd.DataFrame(
        {
            "stroke_p": fp[:, 0],
            "position_p": fp[:, 1],
            "feed_p": fp[:, 2],
            "score": scores,
            "probability": scores / scores.sum(),
        },
        index=pd.Index(clf.classes_, name="condition"),
    )
    table.attrs["motion"] = {k: float(v) for k, v in vals.items()}
    return str(clf.classes_[int(np.argmax(scores))]), table


def format_classification(label: str, table: pd.DataFrame) -> str:
    """A small text table of :func:`classify_motion`'s result."""
    lines = []
    m = table.attrs.get("motion")
    if m:
        lines.append(
            f"motion: stroke {m['stroke_mm']:g} mm, {m['start_mm']:g}-{m['end_mm']:g} mm "
            f"(P_start + P_end = {m['start_mm'] + m['end_mm']:g} mm), feed {m['feed_mm_min']:g} mm/min"
        )
    lines.append(f"{'condition':<10} {'P(stroke)':>9} {'P(pos)':>7} {'P(feed)':>7} {'score':>6} {'prob':>6}")
    for lab, r in table.iterrows():
        mark = "  <-" if str(lab) == str(label) else ""
        lines.append(
            f"{str(lab):<10} {r['stroke_p']:>9.3f} {r['position_p']:>7.3f} {r['feed_p']:>7.3f} "
            f"{r['score']:>6.3f} {r['probability']:>6.3f}{mark}"
        )
    lines.append(f"class: {label}  (seed 002 eq. 19: argmax of the summed level probabilities + prior)")
    return "\n".join(lines)
