"""The figures behind two model-zoo tests, printed in full.

    .venv/bin/python benchmarks/recovery_checks.py

1. Physics identification from noise-free seed 000 data (three Table 2 loadings,
   Pf undeclared, start 35-50 % off): each identified parameter vs Table 3.
2. Seed 001's finding on the five Table 1 moving states (realistic sensors):
   max |residual| / P-V for MLR eq. 12 and the physics model, both trained on state 1.
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from thermbench.config import load_config  # noqa: E402
from thermbench.experiment import cross_condition  # noqa: E402
from thermbench.models.mlr import MLRSeed001  # noqa: E402
from thermbench.models.physics import PhysicsModel  # noqa: E402
from thermbench.sim.parts import CoreParams  # noqa: E402
from thermbench.sim.scenario import simulate_dataset  # noqa: E402

STATES = ["state1", "state2", "state3", "state4", "state5"]


def main() -> None:
    ds, _ = simulate_dataset(load_config("simulate", ["clean=true", "protocol.random_runs.count=0"]))
    ds.metadata.screw.fixed_end_axis_mm = None
    start = dict(k1_W_m2K_per_mm_min=0.5e-3, k2_W_m2K=15.0, lambda_W_mK=300.0, pf_m=-0.08)
    m = PhysicsModel(initial=start).fit(ds)
    truth = CoreParams().as_dict()
    print(f"1. identification from noise-free seed 000 data: {m.identification_s_:.1f} s, "
          f"train RMSE {m.train_rmse_um_:.3f} um")  # fmt: skip
    for k, v in m.core_.as_dict().items():
        print(f"   {k:22s} identified {v:11.5g}  Table 3 {truth[k]:11.5g}  ({(v - truth[k]) / abs(truth[k]):+.2%})")

    ds1, _ = simulate_dataset(load_config("simulate", ["machine=seed001_vmc_x", "protocol=seed001_states", "seed=11"]))
    print("2. seed 001 states, trained on state1: max|residual| / P-V")
    for name, model in [("MLR eq. 12 (degree 4)", MLRSeed001()), ("physics", PhysicsModel())]:
        res = cross_condition(model, ds1, ["state1"], STATES).set_index("run_id")
        print(f"   {name:22s} " + "  ".join(f"{r} {res.loc[r, 'residual_fraction_of_pv']:6.1%}" for r in STATES))


if __name__ == "__main__":
    main()
