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
# # 05 · Bring your own measurements
#
# You have run warm-up tests on a feed axis: a data logger (or the CNC's trace) recorded time, axis
# position, feed and a few thermocouples at 1 Hz, and a laser interferometer measured the positioning
# error at a row of targets every few minutes. This notebook turns those two exports into a thermbench
# dataset (three files, `docs/dataset-format.md`), validates it, shows what the validation says about
# the usual mistakes, and fits a first model.
#
# The measurements here are a stand-in: a few runs of the simulated seed 001 machining centre X axis
# (seed 001 Tables 1-2), re-labelled as a logger and an interferometer would export them. Replace the
# two stand-in frames with `pd.read_csv` of your own files; everything after that is what you would run.

# %% tags=["parameters"]
QUICK = False
OUT_DIR = "../outputs/notebooks/05"
DATA_ROOT = "../data/benchmark"

# %%
import re
import shutil
import subprocess
import sys
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
import pandas as pd
import yaml

from thermbench.data import DatasetError, load_dataset
from thermbench.data.reference import run_summary, thermal_errors
from thermbench.datasets import load_benchmark
from thermbench.experiment import model_from_config
from thermbench.metrics import evaluate

out = Path(OUT_DIR)
out.mkdir(parents=True, exist_ok=True)

# %% [markdown]
# ## Your raw exports (stand-in)
#
# One logger file and one interferometer file per test run, with the column names and local
# timestamps a logger and the interferometer software write. Four runs, each in a loading state of its
# own (stroke, position, feed; two of them with `QUICK`), train the model; the last run, in a loading
# state none of them had, is held out.

# %%
# run id -> (benchmark run standing in for it, day of the test); the conditions go into metadata.yaml below
TESTS = {"r1": ("state1", "2024-03-04"), "r2": ("state4", "2024-03-05"), "r3": ("state5", "2024-03-06"),
         "r4": ("state3", "2024-03-07"), "v1": ("valid1", "2024-03-08")}  # fmt: skip
if QUICK:
    TESTS = {k: TESTS[k] for k in ("r1", "r2", "v1")}
TRAIN_RUNS = [r for r in TESTS if r.startswith("r")]
HELDOUT_RUNS = [r for r in TESTS if r.startswith("v")]
RUN_LENGTH_S = 3 * 3600 if QUICK else None  # QUICK: the first 3 h of each run

stand_in = load_benchmark("seed001_vmc_x", DATA_ROOT)
logger_files, interferometer_files = {}, {}
for run_id, (src, day) in TESTS.items():
    pr, er = stand_in.process_run(src), stand_in.errors_run(src)
    if RUN_LENGTH_S:
        pr, er = pr[pr["t_s"] <= RUN_LENGTH_S], er[er["t_s"] <= RUN_LENGTH_S]
    start = pd.Timestamp(f"{day} 07:00:00")
    logger_files[run_id] = pd.DataFrame({
        "Timestamp": start + pd.to_timedelta(pr["t_s"], unit="s"),
        "X actual [mm]": pr["axis_mm"].round(3), "X feed [mm/min]": pr["feed_mm_min"].round(1),
        "TC1 nut [degC]": pr["T_nut_C"], "TC2 bed [degC]": pr["T_bed_C"], "TC3 air [degC]": pr["T_ambient_C"],
    })  # fmt: skip
    interferometer_files[run_id] = pd.DataFrame({
        "Timestamp": start + pd.to_timedelta(er["t_s"], unit="s"),
        "Target [mm]": er["target_mm"], "Deviation [um]": er["error_um"].round(2),
    })  # fmt: skip
print(logger_files["r1"].head(3).to_string(index=False))
print(interferometer_files["r1"].head(3).to_string(index=False))

# %% [markdown]
# ## The dataset: `process.csv`, `errors.csv`, `metadata.yaml`
#
# The contract's column names carry their units (`_s`, `_mm`, `_mm_min`, `_C`, `_um`). Time is seconds
# since the run's start, on **one clock** for both files: the interferometer reading at `t_s` is matched
# to the logger sample at the same `t_s`. Feed is the speed magnitude (never negative). Each
# temperature column is `<sensor>_C`, one per sensor named in `metadata.yaml`. Readings are the raw
# deviation, not re-zeroed: thermbench subtracts each run's first (cold) measuring cycle itself to get
# the thermal error (seed 002 §3.1).

# %%
process_parts, error_parts = [], []
for run_id, log in logger_files.items():
    interf = interferometer_files[run_id]
    t0 = log["Timestamp"].iloc[0]  # the run's zero, for both files
    process_parts.append(pd.DataFrame({
        "run_id": run_id,
        "t_s": (log["Timestamp"] - t0).dt.total_seconds(),
        "axis_mm": log["X actual [mm]"],
        "feed_mm_min": log["X feed [mm/min]"].abs(),  # a magnitude: abs() if your logger signs it
        "T_nut_C": log["TC1 nut [degC]"],
        "T_bed_C": log["TC2 bed [degC]"],
        "T_ambient_C": log["TC3 air [degC]"],
    }))  # fmt: skip
    error_parts.append(pd.DataFrame({
        "run_id": run_id,
        "t_s": (interf["Timestamp"] - t0).dt.total_seconds(),
        "target_mm": interf["Target [mm]"],
        "error_um": interf["Deviation [um]"],  # measured position minus target, as read
    }))  # fmt: skip
process = pd.concat(process_parts, ignore_index=True)  # rows of a run contiguous, in time order
errors = pd.concat(error_parts, ignore_index=True)

# seed 001 Tables 1-2: the loading state of each run (stroke, start/end of the stroke, feed)
CONDITIONS = {
    "r1": {"stroke_mm": 280, "start_mm": 210, "end_mm": 490, "feed_mm_min": 8000},
    "r2": {"stroke_mm": 210, "start_mm": 0, "end_mm": 210, "feed_mm_min": 8000},
    "r3": {"stroke_mm": 700, "start_mm": 0, "end_mm": 700, "feed_mm_min": 8000},
    "r4": {"stroke_mm": 280, "start_mm": 210, "end_mm": 490, "feed_mm_min": 15000},
    "v1": {"stroke_mm": 280, "start_mm": 0, "end_mm": 280, "feed_mm_min": 8000},
}
metadata = {
    "format": "thermbench-dataset/1",
    "machine": {"name": "my_vmc", "axis": "X"},
    "screw": {"length_m": 1.0, "diameter_m": 0.04, "nut_length_m": 0.15, "fixed_bearing_length_m": 0.04,
              "mounting": "fixed_supported",  # fixed_free | fixed_supported | fixed_fixed
              "fixed_end_axis_mm": -150.0},  # optional: axis coordinate with the nut centre at the fixed end  # fmt: skip
    "material": {"alpha_per_K": 1.17e-5, "density_kg_m3": 7800, "heat_capacity_J_kgK": 460},
    "sensors": {"T_nut": "nut_housing", "T_bed": "bed", "T_ambient": "ambient"},  # -> columns T_nut_C, ...
    "runs": {r: {"condition": CONDITIONS[r], "notes": f"warm-up test {TESTS[r][1]}"} for r in TESTS},
}
# fixed_end_axis_mm is seed 000's Pf (docs/dataset-format.md). The physics model identifies it and only
# starts from the declared value, whose sign picks the side it searches; without it the search assumes
# the fixed end at the low-coordinate side. The seed 001 MLR measures positions from it.


def write_dataset(path, process, errors, metadata):
    """The three files of the dataset format, as you would write them."""
    path = Path(path)
    if path.exists():
        shutil.rmtree(path)
    path.mkdir(parents=True)
    process.to_csv(path / "process.csv", index=False)
    errors.to_csv(path / "errors.csv", index=False)
    (path / "metadata.yaml").write_text(yaml.safe_dump(metadata, sort_keys=False), encoding="utf-8")
    return path


good_dir = write_dataset(out / "my_vmc_x", process, errors, metadata)
for name in ("process.csv", "errors.csv"):
    with open(good_dir / name, encoding="utf-8") as fh:
        print(f"--- {name}\n" + "".join(next(fh) for _ in range(4)))
print("--- metadata.yaml\n" + (good_dir / "metadata.yaml").read_text(encoding="utf-8"))

# %% [markdown]
# ## Load and validate
#
# `load_dataset` reads the three files and checks every rule of the contract; it returns a `Dataset`
# or raises a `DatasetError` naming the file, the column and the row. The run summary shows the
# measured thermal error per run (reading minus the cold reference), a first plausibility check:
# compare its order of magnitude with what a warm-up test of your axis should give (deviations
# written in mm instead of µm come out 1000 times too small). Then look at one run: the axis
# reciprocating over its stroke with a measuring cycle every few minutes, the nut warming faster than
# the bed, and the error growing with the distance from the fixed end while the axis moves, shrinking
# when it stops.
# Leave the temperature spikes and dropouts in the files (the logger's raw readings): every model
# runs the limit and Kalman filters of seed 002 §2.3.1 on them, in Python and in the C runtime.

# %%
ds = load_dataset(good_dir)
print(run_summary(ds).round(1).to_string(index=False))
te = thermal_errors(ds)  # the errors table with thermal_um = reading - cold reference at the same target

# %%
run = TRAIN_RUNS[0]
pr, tr = ds.process_run(run), te[te["run_id"] == run]
fig, ax = plt.subplots(3, 1, figsize=(10, 7.5), sharex=True)
ax[0].plot(pr["t_s"] / 3600.0, pr["axis_mm"], lw=0.3)
ax[0].set_ylabel("axis position, mm")
for col in ds.sensor_columns:
    ax[1].plot(pr["t_s"] / 3600.0, pr[col], lw=0.8, label=f"{col} ({ds.metadata.sensors[col[:-2]]})")
temps_C = pr[ds.sensor_columns].to_numpy()
ax[1].set_ylim(np.percentile(temps_C, 0.1) - 1.0, np.percentile(temps_C, 99.9) + 2.0)  # spikes run off the scale
ax[1].set_ylabel("temperature, °C")
ax[1].legend(fontsize=8)
sc = ax[2].scatter(tr["t_s"] / 3600.0, tr["thermal_um"], c=tr["target_mm"], s=8, cmap="viridis")
fig.colorbar(sc, ax=list(ax), label="interferometer target, mm", pad=0.01)
ax[2].set_ylabel("thermal error, µm")
ax[2].set_xlabel("time, h")
ax[0].set_title(f"run {run} as loaded: motion, temperatures, measured thermal error")
for a in ax:
    a.grid(alpha=0.3)
plt.show()

# %% [markdown]
# The same check from the command line, `thermbench validate DIR` (exit code 0 when valid, 2 with a
# one-line message when not):

# %%
def validate_cli(path):
    res = subprocess.run([sys.executable, "-m", "thermbench", "validate", str(path)], capture_output=True, text=True)
    print(f"$ thermbench validate {path}   # exit code {res.returncode}")
    print(res.stdout + res.stderr)
    return res


assert validate_cli(good_dir).returncode == 0

# %% [markdown]
# ## What the usual mistakes look like
#
# Each case below starts from the good files, makes one mistake as it typically happens, and shows
# the message `load_dataset` (and `thermbench validate`) gives. Row numbers count data rows from 1;
# for CSV the file line is given too (the header is line 1).

# %%
meta_run_missing = {**metadata, "runs": {r: v for r, v in metadata["runs"].items() if r != HELDOUT_RUNS[0]}}
meta_typo = {**metadata, "screw": {**metadata["screw"], "mounting": "fixed-supported"}}

first_v1 = int(np.flatnonzero(process["run_id"] == HELDOUT_RUNS[0])[0])  # first logger row of the held-out run
k = 4000  # a row of run r1, about 67 min after its start
r1_end = int(np.flatnonzero(process["run_id"] == "r1")[-1])
dst = process.copy()  # the logger writes local time, and its clock is set back 1 h during run r1
dst.loc[k:r1_end, "t_s"] -= 3600.0
err_cell = process.astype({"T_bed_C": object})
err_cell.loc[k, "T_bed_C"] = "ERR"  # the logger's text for an open thermocouple
direction = np.sign(process.groupby("run_id")["axis_mm"].diff().fillna(0.0))
signed = process.assign(feed_mm_min=np.where(direction < 0, -process["feed_mm_min"], process["feed_mm_min"]))
k_neg = int(np.flatnonzero(signed["feed_mm_min"] < 0)[0])

MISTAKES = {  # name: (process, errors, metadata as written, what the message must name)
    "forgot the feed column": (process.drop(columns=["feed_mm_min"]), errors, metadata, ["process.csv", "feed_mm_min"]),
    "temperature column without _C": (process.rename(columns={"T_nut_C": "T_nut"}), errors, metadata,
                                        ["process.csv", "T_nut_C"]),
    "text in a number column": (err_cell, errors, metadata, ["process.csv", "T_bed_C", f"row {k + 1}", f"line {k + 2}", "ERR"]),
    "time goes backwards (clock change)": (dst, errors, metadata, ["process.csv", "t_s", f"row {k + 1}", f"line {k + 2}"]),
    "logger at one sample per 2 s": (process.iloc[::2].reset_index(drop=True), errors, metadata,
                                     ["process.csv", "t_s", "row 2", "gap"]),
    "signed velocity as feed": (signed, errors, metadata, ["process.csv", "feed_mm_min", f"row {k_neg + 1}", ">= 0"]),
    "run not declared in metadata": (process, errors, meta_run_missing,
                                     ["process.csv", "run_id", f"row {first_v1 + 1}", repr(HELDOUT_RUNS[0])]),
    "position logged in metres": (process.assign(axis_mm=process["axis_mm"] / 1000.0), errors, metadata,
                                  ["errors.csv", "target_mm", "row ", "outside the travel"]),
    "interferometer clock 1 h ahead": (process, errors.assign(t_s=errors["t_s"] + 3600.0), metadata,
                                       ["errors.csv", "t_s", "row ", "outside the process log"]),
    "mounting misspelt": (process, errors, meta_typo, ["metadata.yaml", "screw.mounting"]),
}  # fmt: skip

def mistake_dir(name):
    return out / "mistakes" / re.sub(r"\W+", "_", name).strip("_")


messages = {}
for name, (p, e, m, needles) in MISTAKES.items():
    bad_dir = write_dataset(mistake_dir(name), p, e, m)
    try:
        load_dataset(bad_dir)
        messages[name] = None  # not caught
    except DatasetError as exc:
        messages[name] = str(exc)
    print(f"[{name}]\n  {messages[name]}")

# %% [markdown]
# Each message says where to look. The fixes: add the column; name temperature columns `<sensor>_C`
# as declared under `sensors:`; write numbers only (a sensor dropout as a number the filters can
# reject, or leave the run out); log in UTC or a monotonic clock; log at 1 Hz or faster; write
# `abs()` of a signed velocity; declare every run; convert positions to mm; put both instruments on
# one clock; spell the mounting as listed.
#
# What no check can catch: a plausible number in the wrong unit (deviations in mm instead of µm,
# temperatures in °F), swapped thermocouples, or a clock offset of a few seconds. Look at the run
# summary and the plots above before trusting a model.
#
# The command line reports the same problem in one line, without a traceback:

# %%
res = validate_cli(mistake_dir("time goes backwards (clock change)"))
assert res.returncode == 2 and "Traceback" not in res.stderr and "process.csv" in res.stderr

# %% [markdown]
# ## A first model on your data
#
# A seed 002 MLR (eq. 6-11: the geometric error separated as a cubic in position, the thermal error a
# line in position whose slope and offset are linear in the temperature rises of sensors chosen by
# seed 002 §2.3.1) is fitted on the training runs and judged on the held-out run.
#
# The plot compares positioning errors: "measured" is the interferometer reading as written to
# `errors.csv`, "predicted" the model's geometric plus thermal part (`predict_at`); their difference
# is the residual the metrics score. The model's thermal part alone (`predict_thermal_at`) is not
# comparable with the measured thermal error: the measured one is zero at the run's cold reference by
# construction, while the model's thermal part is not zero when cold, because the constants of its
# slope and intercept regressions (ΔT = 0) also carry the straight-line part of the cold pitch error
# (seed 002 eq. 8-9 next to eq. 7).

# %%
model = model_from_config("mlr_seed002").fit(ds, TRAIN_RUNS)
print("sensors chosen:", model.required_inputs().sensors)
print(evaluate(model, ds, TRAIN_RUNS + HELDOUT_RUNS)[["run_id", "rmse_um", "max_abs_residual_um", "max_abs_error_um",
                                                      "compensation_rate"]].round(2).to_string(index=False))  # fmt: skip

fig, ax = plt.subplots(1, 2, figsize=(12, 4.2), gridspec_kw={"width_ratios": [1.6, 1]})
for run in HELDOUT_RUNS:
    tr = te[te["run_id"] == run]
    pred_um = model.predict_at(ds, run, tr["t_s"], tr["target_mm"])  # geometric + thermal
    for target_mm, colour in zip((0.0, 350.0, 700.0), ("tab:blue", "tab:orange", "tab:green")):
        sel = (tr["target_mm"] == target_mm).to_numpy()
        t_h = tr["t_s"].to_numpy()[sel] / 3600.0
        ax[0].plot(t_h, tr["error_um"].to_numpy()[sel], "o", color=colour, ms=4, label=f"measured, {target_mm:.0f} mm")
        ax[0].plot(t_h, pred_um[sel], "-", color=colour, label=f"predicted, {target_mm:.0f} mm")
    ax[1].scatter(tr["error_um"], pred_um, s=6, c=tr["target_mm"], cmap="viridis")
held_err_um = te.loc[te["run_id"].isin(HELDOUT_RUNS), "error_um"]
lim_um = [float(held_err_um.min()) - 2, float(held_err_um.max()) + 2]
ax[1].plot(lim_um, lim_um, "k--", lw=1, label="predicted = measured")
ax[0].set_xlabel("time, h")
ax[0].set_ylabel("positioning error, µm")
ax[0].set_title(f"held-out run {', '.join(HELDOUT_RUNS)}: measured vs predicted")
ax[0].legend(fontsize=7, ncol=3)
ax[1].set_xlabel("measured positioning error, µm")
ax[1].set_ylabel("predicted positioning error, µm")
ax[1].set_title("every reading (colour: target)")
ax[1].legend(fontsize=8)
for a in ax:
    a.grid(alpha=0.3)
fig.tight_layout()
plt.show()

# %% [markdown]
# ## The check
#
# The dataset contract promises that a bad dataset is rejected with a message that tells you where the
# problem is: the file, the column (or metadata key) and, for a value, the row (and the CSV line).
# Every typical mistake above must have been caught with such a message.

# %%
for name, (_, _, _, needles) in MISTAKES.items():
    msg = messages[name]
    # why: a message without the file, column and row leaves you searching a 100 000-line CSV by hand;
    # docs/dataset-format.md promises all three, and `thermbench validate` prints exactly this message
    assert msg is not None, f"{name}: not caught"
    missing = [n for n in needles if n not in msg]
    assert not missing, f"{name}: the message does not name {missing}: {msg}"
print(f"all {len(MISTAKES)} mistakes caught; each message names the file, the column or key, and the row of a bad value")
