"""The seed 002 §2.4 classifier figures: Table 6 by eq. 15-19, and the learned classifier's
accuracy on motion it was not trained on (thermbench.bench.classifier_eval).

    .venv/bin/python benchmarks/classifier_checks.py [--seed 0]

Table 6: the class eq. 19 gives for each random condition, next to the paper's.
Learned: scikit-learn GaussianNB (conf/classifier/learned.yaml) fitted as a ConditionBank fits it,
on the online window features (600 s windows every 60 s, measuring cycles excluded) of the seed 002
condition runs c1..c9 (= Table 5 #1..#9); then (a) the class it gives to each Table 6 motion, run
through the simulator's duty cycle and sampled at 1 Hz, against the paper's and eq. 19's, and
(b) its online labels on random duty cycles of c1..c9 (stroke/feed ±15 %, centre ±15 % of the stroke;
again with the centre ±15 % of the 650 mm travel), scored >= 600 s after each switch, with the share
of the first 600 s after a switch already labelled with the new condition.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from thermbench.bench.classifier_eval import (  # noqa: E402
    SEED002_TABLE6,
    duty_cycle_accuracy,
    fit_condition_classifier,
    format_table6,
    run_conditions,
    table5_label_map,
    table6_accuracy,
)
from thermbench.models.classify_one import classify_motion  # noqa: E402
from thermbench.bench.datasets import load_benchmark  # noqa: E402

TABLE6 = [(int(a), int(s), int(e), int(c), paper) for a, s, e, c, paper in SEED002_TABLE6]  # seed 002 Table 6


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=0, help="seed of the random duty cycles (default 0)")
    args = ap.parse_args(argv)
    print("seed 002 Table 6 by eq. 15-19 (conf/classifier/seed002.yaml):")
    for k, (a, s, e, c, paper) in enumerate(TABLE6, 1):
        label, _ = classify_motion(a, s, e, c)
        print(f"  row {k}: stroke {a} mm, {s}-{e} mm, {c} mm/min -> {label} (paper {paper}){'' if label == paper else '  differs'}")
    ds = load_benchmark("seed002_vmc655h_x")
    runs = [f"c{k}" for k in range(1, 10)]
    clf = fit_condition_classifier(ds, runs)
    cond = run_conditions(ds, runs)
    print("\nlearned GaussianNB (trained on c1..c9) on seed 002 Table 6, each motion simulated for 1 h at 1 Hz:")
    print("\n".join("  " + ln for ln in format_table6(table6_accuracy(clf, table5_label_map(cond))).splitlines()))
    for scale in ("stroke", "travel"):
        print()
        print(duty_cycle_accuracy(clf, cond, seed=args.seed, centre_scale=scale).format())


if __name__ == "__main__":
    main()
