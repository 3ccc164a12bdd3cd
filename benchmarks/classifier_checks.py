"""The seed 002 §2.4 classifier figures: Table 6 by eq. 15-19, and the learned classifier's
accuracy on the benchmark's motion logs.

    .venv/bin/python benchmarks/classifier_checks.py

Table 6: the class eq. 19 gives for each random condition, next to the paper's.
Learned: scikit-learn GaussianNB (conf/classifier/learned.yaml) trained on the online window
features of the first half of each seed 002 condition run c1..c9, scored on the second half.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pandas as pd
from hydra.utils import instantiate
from omegaconf import OmegaConf

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from thermbench.classify import classify_motion, learned_features, measuring_intervals, window_features  # noqa: E402
from thermbench.config import config_dir  # noqa: E402
from thermbench.datasets import load_benchmark  # noqa: E402

TABLE6 = [  # stroke, start, end, feed, the paper's class (seed 002 Table 6)
    (100, 60, 160, 1250, "#2"), (30, 60, 90, 4000, "#2"), (320, 400, 720, 500, "#3"), (500, 0, 500, 500, "#3"),
    (20, 610, 630, 300, "#3"), (450, 110, 560, 4300, "#6"), (310, 330, 640, 3400, "#9"),
]


def main() -> None:
    print("seed 002 Table 6 by eq. 15-19 (conf/classifier/seed002.yaml):")
    for k, (a, s, e, c, paper) in enumerate(TABLE6, 1):
        label, _ = classify_motion(a, s, e, c)
        print(f"  row {k}: stroke {a} mm, {s}-{e} mm, {c} mm/min -> {label} (paper {paper}){'' if label == paper else '  differs'}")
    ds = load_benchmark("seed002_vmc655h_x")
    train, test = [], []
    for r in [f"c{k}" for k in range(1, 10)]:
        pr, er = ds.process_run(r), ds.errors_run(r)
        grid = np.arange(pr["t_s"].iloc[0], pr["t_s"].iloc[-1], 60.0)
        w = window_features(pr, grid, exclude=measuring_intervals(pr, er)).assign(t_s=grid)
        w = w[w["moving"]]
        half = w["t_s"] < w["t_s"].median()
        train.append(w[half].assign(y=r))
        test.append(w[~half].assign(y=r))
    train, test = pd.concat(train), pd.concat(test)
    gnb = instantiate(OmegaConf.load(config_dir() / "classifier" / "learned.yaml"), _convert_="all")
    gnb.fit(learned_features(train), train["y"])
    acc = float(np.mean(gnb.predict(learned_features(test)) == test["y"].to_numpy()))
    print(f"learned GaussianNB: {acc:.1%} of {len(test)} second-half windows of c1..c9 labelled correctly")


if __name__ == "__main__":
    main()
