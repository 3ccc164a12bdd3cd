"""The model families every export test fits on seed001_vmc_x (small, fast settings): the host
parity tests (test_export.py) and the target tests (test_target.py) export the same set."""

from __future__ import annotations

from thermbench.models.autoregressive import AutoRegressiveSeed003
from thermbench.models.lssvm import PSOLSSVM
from thermbench.models.mlr import MLRSeed001, MLRSeed002, MLRSeed004
from thermbench.models.neural import GRUModel, MLPModel
from thermbench.models.physics import PhysicsModel

TRAIN = ["state1", "state2", "state3", "state4", "state5"]
HELDOUT = ["valid1", "valid3"]

FAST_PHYSICS = dict(identify=[], dx_m=0.02, dt_s=0.5, macro_dt_s=10.0)


def families():
    return {
        "mlr_seed002": MLRSeed002(),
        "mlr_seed004": MLRSeed004(sensors=["T_nut", "T_bed"], geometric_degree=None),
        "mlr_seed001": MLRSeed001(),
        "lssvm": PSOLSSVM(gamma=100.0, sigma2=2.0, max_samples=400),
        "mlp": MLPModel(hidden=[8, 8], activation="gelu", max_epochs=60, min_epochs=10, patience=20),
        "gru": GRUModel(hidden_size=4, window_s=600.0, step_s=60.0, max_epochs=30, min_epochs=5, patience=10),
        "physics": PhysicsModel(**FAST_PHYSICS),
        "ar_seed003": AutoRegressiveSeed003(operating=["feed_mm_min", "feed_mm_min^2"]),
    }




def shifted_run(ds, run: str, by_s: float):
    """Run ``run`` of ``ds`` alone, its clock moved by ``by_s`` (a float clock far from 0)."""
    from thermbench.data.dataset import Dataset

    pr = ds.process_run(run).assign(t_s=lambda d: d["t_s"] + by_s)
    er = ds.errors_run(run).assign(t_s=lambda d: d["t_s"] + by_s)
    return Dataset(ds.metadata, pr.reset_index(drop=True), er.reset_index(drop=True), path=ds.path)


def double_and_float_at_every_sample(ds, run: str, shift_s: float, replay):
    """The double and the single-precision build's total error at every process sample of ``run``
    moved by ``shift_s``: ``replay(data, queries, exe)`` runs one build (an export's replay_dir)."""
    import pandas as pd

    from thermbench.export import runtime
    from thermbench.export.budget import SINGLE_FLAGS
    from thermbench.export.samples import process_samples

    data = shifted_run(ds, run, shift_s) if shift_s else ds
    s = process_samples(data, run)
    q = pd.DataFrame({"t_s": s["t_s"].to_numpy(), "axis_mm": s["axis_mm"].to_numpy()})
    exes = (runtime.build("tb_replay"), runtime.build("tb_replay", SINGLE_FLAGS))
    return tuple(replay(data, q, e)["total_um"].to_numpy() for e in exes)
