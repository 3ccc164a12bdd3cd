"""thermbench: model and compensate the thermal error of CNC ball-screw feed axes.

Data flows one way: dataset files -> validated dataset (:mod:`thermbench.data`)
-> (preprocess) -> model -> predictions/metrics -> tracking/report/export.
The physics (seed 000 finite-difference ball-screw model and its effects) lives
in :mod:`thermbench.sim`.

Modules that moved to a package of their own keep their old names for one release:
``import thermbench.benchmark`` still gives the module at its new place (the one object, not a
copy), with a :class:`DeprecationWarning` naming it. :data:`MOVED` is the one place a move is
recorded (docs/architecture.md). Names that moved out of a module that stays (a module split in
two) keep working the same way: :data:`MOVED_NAMES` records them, and the old module's
``__getattr__ = thermbench.moved_names(__name__)`` finds each at its new place, with the warning.
"""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.util
import sys
import warnings

__version__ = "0.1.0"

#: old dotted name -> new dotted name
MOVED = {
    "thermbench.summary": "thermbench.report.answer",
    "thermbench.benchmark": "thermbench.bench",
    "thermbench.splits": "thermbench.bench.splits",
    "thermbench.evidence": "thermbench.bench.evidence",
    "thermbench.intervals": "thermbench.bench.intervals",
    "thermbench.adapt": "thermbench.bench.adapt",
    "thermbench.parallel": "thermbench.bench.parallel",
    "thermbench.iso230_report": "thermbench.iso230.report",
    "thermbench._atomic": "thermbench.outputs",
    "thermbench.extras": "thermbench.errors",
    "thermbench.classify": "thermbench.models.classify",
    "thermbench.classifier_eval": "thermbench.bench.classifier_eval",
    "thermbench.datasets": "thermbench.bench.datasets",
    "thermbench.metrics": "thermbench.bench.metrics",
    "thermbench.precompensate_axes": "thermbench.precompensate.axes",
}

#: old module -> {name that moved out of it: the module it is in now}; the old module has
#: ``__getattr__ = moved_names(__name__)`` (a module split in two keeps its names for one release)
MOVED_NAMES: dict[str, dict[str, str]] = {
    "thermbench.data.importer": {
        **dict.fromkeys(["MAPPING_FORMAT", "MAPPING_MAX_BYTES", "MappingError", "ColumnMap", "TimeMap", "ReadOptions",
                         "RunFrom", "FileMap", "AlignMap", "Mapping", "read_mapping"], "thermbench.data.import_mapping"),
        **dict.fromkeys(["UNITS", "ERROR_TARGETS", "unit_of", "RANGES"], "thermbench.data.import_columns"),
        **dict.fromkeys(["ARROW_PROBE_BYTES", "ARROW_RETYPES"], "thermbench.data.import_csv"),
    },
    "thermbench.models.base": {
        "curve_degree": "thermbench.models.separation",
        "choose_sensors": "thermbench.models.sensor_choice",
    },
    "thermbench.models.classify": {
        "classify_motion": "thermbench.models.classify_one",
        "format_classification": "thermbench.models.classify_one",
        "measuring_intervals": "thermbench.models.motion_windows",
        "window_features": "thermbench.models.motion_windows",
        "operating_window_features": "thermbench.models.motion_windows",
    },
    "thermbench.models.physics": {
        "FieldCache": "thermbench.models.physics_runs",
        "PREPARED_PER_RUN": "thermbench.models.physics_runs",
        "gauss_newton": "thermbench.models.polish",
    },
    "thermbench.sim.model": {
        "Drive": "thermbench.sim.prepared", "Prepared": "thermbench.sim.prepared", "Kept": "thermbench.sim.prepared",
        "KEEP_BYTES": "thermbench.sim.prepared", "ReadPlan": "thermbench.sim.history",
        "ThermalHistory": "thermbench.sim.history", "errors_um": "thermbench.sim.history",
    },
    "thermbench.sim.effects": {
        "OPEN_TERMS": "thermbench.sim.open_terms", "effect_class": "thermbench.sim.registry",
        "make_effect": "thermbench.sim.registry", "effects_from_config": "thermbench.sim.registry",
    },
    "thermbench.discrepancy.workflow": {
        "physics_view": "thermbench.discrepancy.job", "PHYSICS_KEYS": "thermbench.discrepancy.job",
        "settings_from_config": "thermbench.discrepancy.job", "check_out_dir": "thermbench.discrepancy.job",
        "load_for_diagnosis": "thermbench.discrepancy.job", "diagnose": "thermbench.discrepancy.job",
        "more_data": "thermbench.discrepancy.search",
    },
    "thermbench.discrepancy.search": {
        "SignificanceTest": "thermbench.discrepancy.significance", "bic": "thermbench.discrepancy.significance",
        "explained": "thermbench.discrepancy.significance", "decide": "thermbench.discrepancy.significance",
        "display": "thermbench.discrepancy.significance",
    },
    "thermbench.cli": {
        **dict.fromkeys(["cmd_certs", "cmd_classify", "cmd_compensator", "cmd_diagnose", "cmd_import", "cmd_iso230",
                         "cmd_linuxcnc", "cmd_precompensate", "cmd_replay", "cmd_sim_cnc", "cmd_simulate", "cmd_station",
                         "cmd_validate"], "thermbench.cli.commands"),
        "HYDRA_JOBS": "thermbench.cli.parser",
    },
    "thermbench.report.markdown": dict.fromkeys(["PROBES_MD", "HOW_TO_READ", "HOW_TO_READ_BASELINES",
                                                 "HOW_TO_READ_CHANNELS"], "thermbench.report.details"),
    "thermbench.report.tables": dict.fromkeys(["CURVE_COLUMNS", "KINDS", "RESULT_COLUMNS"], "thermbench.bench.results"),
    "thermbench.compensator.control": {
        "Deadlines": "thermbench.compensator.deadlines",
        "Settings": "thermbench.compensator.settings",
        "config_error": "thermbench.compensator.settings",
        "Line": "thermbench.compensator.errorline",
        "fit_line": "thermbench.compensator.errorline",
    },
    "thermbench.export.bundle": {
        "MANIFEST": "thermbench.export.directory",
        "FORMAT": "thermbench.export.directory",
        "read_manifest": "thermbench.export.directory",
        "replay_inputs": "thermbench.export.directory",
        "replay_dir": "thermbench.export.directory",
        "process_samples": "thermbench.export.samples",
        "readings_queries": "thermbench.export.samples",
        "write_onnx": "thermbench.export.onnxfile",
        "python_predictions": "thermbench.export.parity",
        "TargetRefused": "thermbench.export.budget",
        "TARGETS": "thermbench.export.budget",
        "SINGLE_FLAGS": "thermbench.export.budget",
        "BUDGET": "thermbench.export.budget",
        "SMALL_KINDS": "thermbench.export.budget",
        "footprint": "thermbench.export.budget",
    },
    "thermbench.linuxcnc.sim": {"SAMPLED": "thermbench.linuxcnc.verify"},
}


def _say_moved(old: str, new: str) -> None:
    warnings.warn(f"{old} has moved to {new}: import it from there; the old name goes in the next release",
                  DeprecationWarning, stacklevel=3)


def moved_names(module: str):
    """The module-level ``__getattr__`` of ``module``: a name of ``MOVED_NAMES[module]`` is looked up
    in the module it moved to, with a :class:`DeprecationWarning` naming that place; any other name
    is an AttributeError, as without it."""
    names = MOVED_NAMES.get(module, {})

    def __getattr__(name: str):
        if name not in names:
            raise AttributeError(f"module {module!r} has no attribute {name!r}")
        _say_moved(f"{module}.{name}", names[name])
        return getattr(importlib.import_module(names[name]), name)

    return __getattr__


class _MovedFinder(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    """Finds an old name of :data:`MOVED` and loads the module at its new name in its place."""

    def find_spec(self, fullname, path=None, target=None):
        if fullname not in MOVED:
            return None
        return importlib.util.spec_from_loader(fullname, self)

    def create_module(self, spec):
        return None  # a placeholder: exec_module puts the real module in its place

    def exec_module(self, module) -> None:
        new = MOVED[module.__name__]
        _say_moved(module.__name__, new)
        # the import system returns what sys.modules holds under the name after exec_module: the module itself,
        # so the old and the new name are one object (a monkeypatch through either is seen by both)
        sys.modules[module.__name__] = importlib.import_module(new)


def install() -> None:
    """Put the finder on ``sys.meta_path`` (once)."""
    if not any(isinstance(f, _MovedFinder) for f in sys.meta_path):
        sys.meta_path.append(_MovedFinder())


install()  # old module names (thermbench.benchmark, ...) keep working for one release
