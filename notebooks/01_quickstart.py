# ---
# jupyter:
#   jupytext:
#     formats: py:percent
#   kernelspec:
#     display_name: Python 3
#     language: python
#     name: python3
# ---

# %% [markdown]
# # 01 · Quickstart: simulate an axis, fit two model families, compare them
#
# A ball screw heats up from the friction of its nut and bearings, grows by tens of
# micrometres, and the axis misses its targets. This notebook goes through the whole loop on
# one simulated machine:
#
# 1. **simulate** a measured dataset: the X axis of the seed 001 vertical machining centre
#    run through the seed 001 loading states (Table 1: five modelling states; Table 2: four
#    validation states), with sensor noise, interferometer noise and a pitch error;
# 2. **fit two model families** on some of the states: the seed 002 multiple linear
#    regression (temperature sensors in, error out) and the identified physics model (the
#    seed 000 finite-difference screw model with its heat-transfer coefficients fitted,
#    driven by the motion log and the ambient sensor only);
# 3. **compare** them on the validation runs, which the models never saw.
#
# Everything below uses the public API; the same runs are available from the command line
# (`thermbench simulate`, `thermbench train`, `thermbench evaluate`).

# %% tags=["parameters"]
QUICK = False  # True: small settings (fewer training states, fewer optimiser iterations)
OUT_DIR = "../outputs/notebooks/01"
DATA_ROOT = "../data/benchmark"  # not used here: this notebook simulates its own dataset into OUT_DIR
SEED = 0

# %%
from pathlib import Path

import matplotlib.pyplot as plt
import pandas as pd

from thermbench.bench import datasets
from thermbench.data.reference import run_summary, thermal_errors
from thermbench.experiment import fit_evaluate, model_from_config

out = Path(OUT_DIR)
out.mkdir(parents=True, exist_ok=True)

# %% [markdown]
# ## 1. Simulate a measured dataset
#
# `datasets.simulated` runs `thermbench simulate` for a machine × protocol (both in `conf/`)
# and caches the dataset by the hash of its configuration. `truth="benchmark"` adds the
# effects a real axis has beyond the seed 000 core model (docs/benchmark-truth.md); the
# instruments are the realistic ones of `conf/instruments/realistic.yaml`.

# %%
ds = datasets.simulated(machine="seed001_vmc_x", protocol="seed001_states", seed=SEED, root=out / "data")
print(ds.path)
run_summary(ds).round(2)

# %% [markdown]
# A run is a loading state: the nut reciprocates over a stroke at a feed, and every few minutes the
# axis stops at the measuring positions where the interferometer reads the positioning error.
# The **thermal** error is the reading minus the run's first (cold) reading at the same target
# (seed 002 §3.1). Here is one modelling state: the temperatures the machine logs and the thermal
# error they come with. The spikes are sensor artefacts the realistic instruments add (dropouts to
# 85 °C, single-sample spikes); the models filter them (seed 002 §2.3.1 limit + Kalman filter).

# %%
run = "state1"
proc = ds.process_run(run)
te = thermal_errors(ds)
te_run = te[te["run_id"] == run]

fig, (a1, a2) = plt.subplots(1, 2, figsize=(11, 3.6))
for col in ds.sensor_columns:
    a1.plot(proc["t_s"] / 3600, proc[col], lw=1, label=col)
a1.set(xlabel="time (h)", ylabel="temperature (°C)", title=f"{run}: logged temperatures")
a1.legend(fontsize=7, ncol=2)
for target_mm, g in te_run.groupby("target_mm"):
    if target_mm % 200 == 0:
        a2.plot(g["t_s"] / 3600, g["thermal_um"], "o-", ms=3, label=f"{target_mm:.0f} mm")
a2.set(xlabel="time (h)", ylabel="thermal error (µm)", title=f"{run}: measured thermal error")
a2.legend(fontsize=7, title="target")
fig.tight_layout()
plt.show()

# %% [markdown]
# ## 2. Fit two model families
#
# Both come from their `conf/model/*.yaml` (`model_from_config`), exactly as `thermbench train
# model=...` builds them. `fit_evaluate` fits a copy on the training runs and scores it on every
# run of the dataset (residual = measured − predicted; compensation rate = 1 − max|residual| /
# max|thermal error|, seed 000 §5).
#
# * **MLR (seed 002 §2.3)**: picks the temperature-sensitive points, then a linear model of the
#   thermal error in the sensor temperatures and the position, plus a cubic geometric error.
# * **Physics (seed 000 §4.2)**: the finite-difference screw model. The convection coefficients k1, k2,
#   the conductivity λ and Pf (the axis coordinate at which the nut centre is at the fixed end) are
#   searched by SLSQP; the heat gains k3, k4 are solved by bounded linear least squares at each step.
#   It needs no sensor on the screw: only where and how fast the axis moved and the ambient temperature.

# %%
train = ["state1"] if QUICK else ["state1", "state3", "state5"]
families = {"MLR (seed 002)": model_from_config("mlr_seed002"), "physics (seed 000)": model_from_config("physics")}
if QUICK:
    families["physics (seed 000)"].set_params(max_iter=8)

fitted, rows, curves = {}, [], []
for label, model in families.items():
    m, res, cur = fit_evaluate(model, ds, train, curves=True)
    fitted[label] = m
    rows.append(res.assign(family=label))
    curves.append(cur.assign(family=label))
    print(f"{label}: fitted on {train} in {res['fit_s'].iloc[0]:.1f} s")
results = pd.concat(rows, ignore_index=True)
curves = pd.concat(curves, ignore_index=True)

# %% [markdown]
# ## 3. Compare on the validation runs (loading states not trained on)

# %%
validation = [r for r in ds.run_ids if r.startswith("valid")]
table = results[results["run_id"].isin(validation)].pivot(index="run_id", columns="family",
                                                           values=["rmse_um", "max_abs_residual_um", "compensation_rate"])
table.round(3)

# %% [markdown]
# Before and after compensation, per measuring cycle: black is the largest uncompensated thermal
# error of the cycle, the coloured lines the largest residual left by each model.

# %%
fig, axes = plt.subplots(1, len(validation), figsize=(3.2 * len(validation), 3.2), sharey=True)
for ax, run in zip(axes, validation):
    c = curves[curves["run_id"] == run]
    first = c[c["family"] == next(iter(families))]
    ax.plot(first["t_s"] / 3600, first["before_um"], color="black", lw=2, label="uncompensated")
    for label, g in c.groupby("family"):
        ax.plot(g["t_s"] / 3600, g["after_um"], "o-", ms=2, label=label)
    ax.set(title=run, xlabel="time (h)")
axes[0].set_ylabel("max |error| in cycle (µm)")
axes[-1].legend(fontsize=7)
fig.tight_layout()
plt.show()

# %% [markdown]
# And what the models predict at one position of one validation run, against the measurement:

# %%
run, target_mm = validation[0], 200.0
er = te[(te["run_id"] == run) & (te["target_mm"] == target_mm)]
fig, ax = plt.subplots(figsize=(6.5, 3.4))
ax.plot(er["t_s"] / 3600, er["error_um"], "ko", ms=4, label="measured")
t_s = ds.process_run(run)["t_s"].to_numpy()[::60]  # the prediction is continuous in time
for label, m in fitted.items():
    ax.plot(t_s / 3600, m.predict_at(ds, run, t_s, target_mm), lw=1.5, label=label)
ax.set(xlabel="time (h)", ylabel="positioning error (µm)", title=f"{run} at {target_mm:.0f} mm")
ax.legend(fontsize=8)
plt.show()

# %% [markdown]
# ## Check
# The thermal error is the reading minus the run's cold reading at the same target: what is left
# after a plain pitch-error table (geometric compensation only). A thermal model that leaves more
# than that would be useless: on every validation run each family must leave an RMS residual below
# the RMS of the thermal error, and a positive compensation rate.

# %%
for (label, run), r in results.set_index(["family", "run_id"]).loc[:, ["rmse_um", "compensation_rate"]].iterrows():
    if run in validation:
        th = te.loc[te["run_id"] == run, "thermal_um"]
        assert r["rmse_um"] < (th**2).mean() ** 0.5, (label, run)
        assert r["compensation_rate"] > 0, (label, run)
print("both families compensate every validation run")

# %% [markdown]
# Next: **02** asks how each family holds up in a loading state it was not trained on,
# state by state; **04** exports the fitted model for the embedded compensator.
