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
# # 02 · Robustness: how well does a model hold up in a loading state it was not trained on?
#
# A thermal-error model is fitted on a few loading states, but the machine then runs whatever the
# part programme asks. Seed 001 (§5.1) fits a model on one loading state (M1 on state 1) and shows how
# much worse it does on the other states; seed 002 (§2.4-2.5) answers with a **bank**: one
# model per known condition and a naive-Bayes classifier that picks the model from the motion.
#
# This notebook runs that comparison for a few model families on the seed 001 benchmark dataset
# (five modelling states, four validation duty cycles), in three approaches:
#
# * **single**: trained on one state, tested on every state (the train × test matrix);
# * **global**: trained on all modelling states at once;
# * **bank**: the single-state models behind a condition classifier (seed 002 eq. 15-19).
#
# It is `thermbench benchmark datasets=[seed001_vmc_x]` in miniature, through the same function
# (`thermbench.bench.run.run_task`) the benchmark calls for each dataset × family.

# %% tags=["parameters"]
QUICK = False  # True: the two MLR families only (the physics family takes minutes)
OUT_DIR = "../outputs/notebooks/02"
DATA_ROOT = "../data/benchmark"
SEED = 0

# %%
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
import pandas as pd

from thermbench import report
from thermbench.bench import run_task
from thermbench.experiment import group_option

Path(OUT_DIR).mkdir(parents=True, exist_ok=True)
families = ["mlr_seed001", "mlr_seed002"] if QUICK else ["mlr_seed001", "mlr_seed002", "lssvm", "physics"]

# %% [markdown]
# The dataset and the classifier are the `conf/` options the benchmark uses
# (`conf/dataset/seed001_vmc_x.yaml`, `conf/classifier/proximity.yaml`); the dataset is built on
# first use and cached under `DATA_ROOT`.

# %%
dataset_cfg = group_option("dataset", "seed001_vmc_x")
dataset_cfg["source"]["root"] = DATA_ROOT
classifier_cfg = group_option("classifier", "proximity")
print("modelling states:", dataset_cfg["states"], "| validation runs:", dataset_cfg["validation"])

tasks = {}
for fam in families:
    approaches = ["single", "global"] + (["bank"] if fam != "physics" else [])  # physics reads the motion itself
    tasks[fam] = run_task(dataset_cfg, fam, group_option("model", fam), approaches, classifier_cfg, seed=SEED)
    print(f"{fam}: {tasks[fam]['seconds']:.1f} s", *tasks[fam]["errors"])
results = pd.concat([t["results"] for t in tasks.values()], ignore_index=True)
results[["family", "approach", "train", "run_id", "kind", "rmse_um", "compensation_rate"]].head()

# %% [markdown]
# ## The train × test matrix
#
# Rows: the state a single-state model was trained on; columns: the state it was tested on.
# The diagonal is each model on its own data; everything else is a loading state it never saw.
# Cells show the compensation rate 1 − max|residual| / max|thermal error| (seed 000 §5); a negative
# rate (colour clipped at 0) means the "compensated" axis is worse than the uncompensated one.

# %%
fig, axes = plt.subplots(1, len(families), figsize=(4.6 * len(families), 4.0), squeeze=False, layout="constrained")
for ax, fam in zip(axes[0], families):
    m = report.train_test_matrix(results, "seed001_vmc_x", fam)
    im = ax.imshow(m.to_numpy(), vmin=0, vmax=1, cmap="RdYlGn")
    for i in range(m.shape[0]):
        for j in range(m.shape[1]):
            ax.text(j, i, f"{100 * m.iat[i, j]:.0f} %", ha="center", va="center", fontsize=8,
                    fontweight="bold" if m.index[i] == m.columns[j] else "normal")
    ax.set_xticks(range(m.shape[1]), m.columns, rotation=45)
    ax.set_yticks(range(m.shape[0]), m.index)
    ax.set(title=fam, xlabel="tested on", ylabel="trained on")
fig.colorbar(im, ax=axes[0].tolist(), label="compensation rate", shrink=0.8)
plt.show()

# %% [markdown]
# ## Single vs global vs bank on the validation duty cycles
#
# `report.approach_comparison` summarises each family on the validation runs: the best, mean and
# worst single-state model (which state was best is only known after the fact), the global model
# and the bank.

# %%
comp = report.approach_comparison(results, "seed001_vmc_x")
comp.round(3)

# %%
fig, ax = plt.subplots(figsize=(8, 0.34 * len(comp) + 1.4), layout="constrained")
y = np.arange(len(comp))
ax.hlines(y, comp["worst_rate"], comp["mean_rate"], color="grey", lw=1)
ax.plot(comp["mean_rate"], y, "o", color="tab:blue", label="mean over the validation runs")
ax.plot(comp["worst_rate"], y, "s", color="tab:red", label="worst validation run")
ax.set_yticks(y, [f"{fam} · {model}" for fam, model in comp.index])
ax.invert_yaxis()
ax.set(xlabel="compensation rate", title="seed001_vmc_x: validation duty cycles")
ax.grid(axis="x", alpha=0.3)
ax.legend(fontsize=8)
plt.show()

# %% [markdown]
# What a model trained on one state leaves on an unseen state, over time: the best and the worst
# single-state models of the first family on the validation run where they differ most, against
# the global model.

# %%
fam = families[0]
single = results[(results["family"] == fam) & (results["approach"] == "single") & (results["kind"] == "validation")]
rate = single.pivot(index="train", columns="run_id", values="compensation_rate")
run = (rate.max() - rate.min()).idxmax()
best, worst = rate[run].idxmax(), rate[run].idxmin()

from thermbench.bench.datasets import load_benchmark
from thermbench.experiment import fit_evaluate, model_from_config
from thermbench.bench.metrics import evaluate

ds = load_benchmark("seed001_vmc_x", DATA_ROOT)
fig, ax = plt.subplots(figsize=(7, 3.5))
for label, train in {f"trained on {best}": [best], f"trained on {worst}": [worst], "global": dataset_cfg["states"]}.items():
    m, _, _ = fit_evaluate(model_from_config(fam), ds, train)
    _, cur = evaluate(m, ds, [run], curves=True)
    ax.plot(cur["t_s"] / 3600, cur["after_um"], "o-", ms=2, label=label)
ax.plot(cur["t_s"] / 3600, cur["before_um"], color="black", lw=2, label="uncompensated")
ax.set(xlabel="time (h)", ylabel="max |error| in cycle (µm)", title=f"{fam} on {run}")
ax.legend(fontsize=8)
plt.show()

# %% [markdown]
# ## Check
# Seed 001's point (§5.1) is that a model fitted on one loading state does worse on the others than
# on its own data. That must show in the matrix: for every family, the mean rate on the unseen
# (off-diagonal) states is below the mean rate on the own (diagonal) states. And the global
# model, which saw all modelling states, must not be worse on average over the validation runs than
# the average single-state model.

# %%
for fam in families:
    m = report.train_test_matrix(results, "seed001_vmc_x", fam).to_numpy()
    own, unseen = np.nanmean(np.diag(m)), np.nanmean(m[~np.eye(len(m), dtype=bool)])
    print(f"{fam}: own states {own:.3f}, unseen states {unseen:.3f}")
    assert unseen < own, fam
    assert comp.loc[(fam, "global"), "mean_rate"] >= comp.loc[(fam, "single mean"), "mean_rate"] - 1e-9, fam
