"""The robustness comparison (the user's main question): how well does each model family
hold up in a loading state it was not trained on?

For each dataset (``conf/dataset``: its loading ``states`` and its ``validation`` runs) and
each family (``conf/model``), one task (:func:`run_task`) fits

* ``single``: one model per loading state, scored on every run — the train-state x
  test-state matrix (seed 001 §5: regression fails across moving states);
* ``global``: one model on all loading states;
* ``bank``: the single-state models behind a condition classifier (seed 002 §2.4,
  :class:`thermbench.models.bank.ConditionBank`), reusing the single fits;
* ``bank_soft``: the same members blended by the classifier's probabilities instead of
  switched by its label;

and scores them on the validation duty cycles (seed 001 Table 2, seed 002 Table 6,
seed 000's random cycle; the measured spindle test's stepped tail), the seeds' headline:
compensation rate and max residual on unseen cycles. A format 2 dataset with several error
channels (``channel: null`` in its option) is benchmarked on each channel: one task per
(dataset, channel, family); the results' ``channel`` column names it (``all`` for a format 1
dataset). Tasks run in parallel (joblib), each cached on disk by its arguments
(joblib.Memory), so an interrupted benchmark resumes where it stopped. Each of the ``n_jobs``
workers runs its fits on its share of the job's cores
(:func:`thermbench.bench.parallel.worker_threads`), so parallel tasks never oversubscribe them.

The package, one duty per module, in the order data flows: :mod:`.splits` (the runs a dataset
is split into, folds over whole runs) → :mod:`.plan` (the settings checked, the tasks) →
:mod:`.run` (a task: every approach and fold fitted and scored, in parallel) with
:mod:`.calibration` (each fold's intervals and probe replays: :mod:`.intervals`, :mod:`.adapt`)
→ :mod:`.choice` (the one selection rule and the held-out figures of it) and :mod:`.evidence`
(what limits the held-out error) → :mod:`.job` (the report, MLflow, the models).
:mod:`.results` holds the schema of the frames they pass on (results.csv's columns and their
checks); :mod:`.parallel` runs the workers.

The names below are importable from the package itself (``from thermbench.bench import
run_task``); each is loaded from its module on first use, so importing a light module of the
package (e.g. :mod:`.splits`) does not import the job.
"""

from __future__ import annotations

import importlib
import importlib.util
import pkgutil

#: public name -> the module of the package that defines it
_WHERE = {
    "benchmark": "job",
    "run_task": "run", "failure_text": "run",
    "tasks": "plan", "families_by_dataset": "plan", "channels_of": "plan", "case_label": "plan", "model_config": "plan",
    "family_class": "plan", "family_lacks": "plan", "reference_only": "plan", "reference_only_model": "plan",
    "interval_settings": "plan", "output_name": "plan", "output_dirs": "plan", "plain_value": "plan",
    "DEPLOY_FOLD": "plan", "CELL_FAILURES": "plan", "BANKS": "plan", "APPROACHES": "plan",
    "calibrate_fold": "calibration", "fold_intervals": "calibration", "probe_results": "calibration",
    "gp_refit_results": "calibration", "probe_approach": "calibration", "probe_rows": "calibration",
    "PROBE_PREFIXES": "calibration",
    "choose": "choice", "model_complexity": "choice", "nested_choice": "choice", "deployed_choice": "choice",
    "held_out_summary": "choice", "held_out_table": "choice", "held_out_flags": "choice", "flagged": "choice",
    "held_out_limits": "evidence",
}  # fmt: skip
__all__ = sorted(_WHERE)


def __getattr__(name: str):
    if importlib.util.find_spec(f"{__name__}.{name}") is not None:  # a module of the package, loaded on first use
        return importlib.import_module(f".{name}", __name__)
    if name in _WHERE:
        value = getattr(importlib.import_module(f".{_WHERE[name]}", __name__), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_WHERE) | {m.name for m in pkgutil.iter_modules(__path__)})
