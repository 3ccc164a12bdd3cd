"""The robustness report: how well each thermal-error model family holds up when
the machine runs in a loading state it was not trained on.

Seed 001 §5 found that a regression model fitted on one moving state fails on
the others while the heat-transfer model holds; seed 002 §3.1.2/§3.2 answers the
same weakness with a bank of per-condition models and a condition classifier
(§2.4), reporting the gain as a compensation rate (88.69 % own condition,
70.67 % PSO-LSSVM, 53.11 % with classification). This module turns the
benchmark's long results table into those numbers, per dataset, error channel,
family and approach, on the runs each model has *not* seen.

Inputs (built by the benchmark; checked by :mod:`thermbench.bench.results`, a missing column is a ValueError
naming it and the frame):

``results``
    One row per (fitted model, test run): ``dataset``, ``family``, ``approach``
    (``single`` = trained on one loading state, ``global`` = one model on all
    states, ``bank`` / ``bank_soft`` = per-state models + condition classifier,
    switched / blended), ``train`` (the training run for ``single``, ``all``
    otherwise), ``run_id``, ``kind`` (``state`` = modelling state, ``validation``
    = validation duty cycle), ``own`` (the test run was in the training set) and
    the metrics of :func:`thermbench.bench.metrics.residual_metrics`
    (``compensation_rate`` is a fraction, 1 − max|residual| / max|thermal error|,
    seed 000 §5, seed 002 §3; ``rmse_um`` is needed for a dataset with several
    channels). Optional ``channel``: the error channel the model was fitted to
    (``ch1`` … of a format 2 dataset; ``all`` for a format 1 dataset; a missing
    column or value means ``all``). A fitted model is one (dataset, channel,
    family, approach, train); each is scored once per test run.
``curves``
    Before/after compensation per measuring cycle: ``dataset``, ``family``,
    ``approach``, ``run_id``, ``t_s``, ``before_um`` (max |thermal error| of the
    cycle, uncompensated), ``after_um`` (max |residual| after compensation);
    optionally ``train`` to tell several single-state models apart and
    ``channel`` (missing = ``all``).

"Unseen" runs are the rows with ``own`` false: the validation cycles for every
approach and, for single-state models, the other modelling states (the
off-diagonal cells of the train × test matrix).

Report directory (:func:`write_report`): ``report.md`` (the answer: the model to deploy per
dataset and channel and its held-out error), ``details.md`` (the tables and figures behind it),
``findings.md`` (the run's lists of findings, e.g. the flagged models), ``figures/*.png`` and
``results.csv``, one row per (fitted model, test run), columns in this order:

``dataset, family, approach, train, test, channel, rmse_um, max_abs_residual_um,
compensation_rate, kind, own, reference``, then the other columns of ``results``
in their order (e.g. ``pv_residual_um, max_abs_error_um, pv_error_um,
residual_fraction_of_pv, nonfinite_predictions, fit_s``). ``test`` is the run
scored (``run_id``: a loading state or a validation run such as ``tail``),
``channel`` the error channel (``all`` for a format 1 dataset), ``reference``
true for a baseline family (compared, never chosen); ``rmse_um`` is empty when
``results`` has no such column. Rows are in report order (dataset, channel,
family, approach single/global/bank/bank_soft, then as given).

A dataset scored on several channels gets its own layout (:func:`write_report`):
validation RMSE per channel (table with the best per channel and the best
thermbench family vs the best baseline), a bar chart of it, one train × test
RMSE heatmap per family (a panel per channel) and the before/after curves of
the best model per channel. Format 1 and single-channel datasets keep the
compensation-rate layout.

Public API: :func:`train_test_matrix`, :func:`headline`,
:func:`approach_comparison`, :func:`validation_by_channel`,
:func:`best_by_channel`, :func:`terminal_summary`, :func:`write_report`,
:func:`results_table` (the rows of results.csv), :func:`figure_paths`,
:func:`markdown_table`.

The package, one duty per module, data flowing one way: :mod:`.tables` (pure pandas: what the
report shows, computed from the results) → :mod:`.text` (number formats, markdown tables, the
terminal summary) and :mod:`.figures` (matplotlib only) → :mod:`.details` (details.md's sections)
→ :mod:`.markdown` (the files: :func:`write_report`); :mod:`.answer` is the first screen (the model to deploy per dataset and
channel, its held-out error and interval), shared by the report, the terminal and MLflow.
"""

from .figures import curves_figure, probe_figure
from .markdown import (
    CSV_NAME, DETAILS_NAME, FIGURES_DIR, FINDINGS_NAME, REPORT_NAME, figure_paths, write_report,
)
from ..bench.results import ALL_CHANNELS, CHANNEL, CSV_COLUMNS, CURVE_COLUMNS, RATE, RESIDUAL, RESULT_COLUMNS, RMSE
from .tables import (
    approach_comparison, best_by_channel, headline, probe_curve, results_table, train_test_matrix,
    validation_by_channel,
)
from .text import fmt_rate, fmt_um, markdown_table, terminal_summary

__all__ = [
    "ALL_CHANNELS", "CHANNEL", "CSV_COLUMNS", "CSV_NAME", "CURVE_COLUMNS", "DETAILS_NAME", "FIGURES_DIR",
    "FINDINGS_NAME", "RATE", "REPORT_NAME", "RESIDUAL", "RESULT_COLUMNS", "RMSE", "approach_comparison",
    "best_by_channel", "curves_figure", "figure_paths", "fmt_rate", "fmt_um", "headline", "markdown_table",
    "probe_curve", "probe_figure", "results_table", "terminal_summary", "train_test_matrix",
    "validation_by_channel", "write_report",
]
