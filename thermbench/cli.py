"""``thermbench`` command line: a thin layer over importable functions.

    thermbench simulate [hydra overrides...]   write a dataset (or suite=benchmark: all standard ones)
    thermbench validate DATA_DIR               check a dataset against the contract and summarise it
    thermbench import MAPPING.yaml --out DIR [--format csv|parquet] [--force]
                                               a lab's own files (CSV, Excel, Parquet) -> a dataset (docs/import.md)
    thermbench iso230 DATA_DIR --out DIR [--force]
                                               ISO 230-2 / 230-3 figures of a thermal test (docs/iso230.md)
    thermbench classify --stroke S --start A --end B --feed F
                                               seed 002 §2.4 condition classifier: the chosen condition
    thermbench diagnose DATA_DIR --out OUT_DIR [--base EFFECT,...] [--max-effects K] [overrides...]
                                               discrepancy workflow: name the effect the physics model misses
    thermbench replay MODEL_DIR DATA_DIR --run ID [--probes FILE] [--out OUT_DIR] [--force]
                                               an exported model in the C runtime over a run's log: before/after
    thermbench precompensate PROGRAM.nc --model MODEL.joblib --out OUT.nc [--verify] [...]
    thermbench precompensate PROGRAM.nc --models axes.yaml --out OUT.nc [--verify] [...]
                                               seed 003: rewrite a part program against the predicted error
    thermbench compensator MODEL_DIR --endpoint opc.tcp://HOST:PORT --nodes nodes.yaml [overrides...]
                                               OPC UA compensator: the exported model against a live machine
    thermbench sim-cnc [--endpoint URL] [overrides...]
                                               a simulated CNC axis behind an OPC UA server (closed loop)
    thermbench certs OUT_DIR                   self-signed certificates for Basic256Sha256 sign-and-encrypt
    thermbench train|evaluate|benchmark|export [hydra overrides...] [-m]
                                               Hydra jobs (thermbench.app): conf/<job>.yaml
"""

from __future__ import annotations

import argparse
import difflib
import math
import signal
import sys
import warnings
from pathlib import Path

from . import __version__


def _print_summary(title: str, path: Path, table) -> None:
    print(f"\n{title}  ->  {path}")
    show = table[["run_id", "duration_h", "stroke_mm", "start_mm", "end_mm", "feed_mm_min", "max_thermal_error_um"]]
    print(show.to_string(index=False, float_format=lambda v: f"{v:.1f}"))


def cmd_simulate(overrides: list[str]) -> int:
    from .config import ConfigError, compose_checked

    cfg = compose_checked("simulate", overrides)  # first: a mistake is reported before the simulator loads
    from .bench import datasets
    from .data.io import load_dataset, save_dataset
    from .data.reference import run_summary
    from .sim.scenario import simulate_dataset

    if cfg.get("suite") == "benchmark":
        from .outputs import check_output_dir

        root = Path(str(cfg.benchmark_root))
        for name in datasets.names():  # every target checked before the first simulation
            check_output_dir(root / name, "dataset", force_option="")
        for name in datasets.names():
            path, built = datasets.build(name, root)
            ds = load_dataset(path)
            state = "built" if built else "cached (config hash matches)"
            _print_summary(f"[{name}] {state}", path.resolve(), run_summary(ds))
        return 0
    if cfg.get("suite") is not None:
        raise ConfigError(f"config key 'suite': expected null or 'benchmark', got {cfg.suite!r}")
    # checked here, before the simulation runs (minutes), not when its result is saved
    if cfg.file_format not in ("csv", "parquet"):
        raise ConfigError(f"config key 'file_format': expected csv or parquet, got {cfg.file_format!r}")
    if not isinstance(cfg.seed, int) or isinstance(cfg.seed, bool) or cfg.seed < 0:
        raise ConfigError(f"config key 'seed': expected an integer >= 0, got {cfg.seed!r}")
    from .outputs import check_output_dir

    force = cfg.get("force", False)
    if not isinstance(force, bool):
        raise ConfigError(f"config key 'force': expected true or false, got {force!r}")
    check_output_dir(Path(str(cfg.out_dir)), "dataset", force=force, force_option="force=true")  # before simulating
    ds, _ = simulate_dataset(cfg)
    path = save_dataset(ds, Path(str(cfg.out_dir)), file_format=str(cfg.file_format), force=force)
    _print_summary(f"[{cfg.machine.name} / {cfg.protocol.name}] simulated", path.resolve(), run_summary(load_dataset(path)))
    return 0


def cmd_validate(path: str) -> int:
    from .data.io import load_dataset
    from .data.reference import run_summary

    ds = load_dataset(path)
    meta = ds.metadata
    if meta.version == 1:
        print(f"{path}: valid {meta.format} dataset, machine {meta.machine.name} axis {meta.machine.axis}")
        print(f"  {len(ds.process)} process rows, {len(ds.errors)} error readings, sensors: {', '.join(ds.sensor_columns)}")
        _print_summary("runs", Path(path).resolve(), run_summary(ds))
        return 0
    _print_v2(path, ds, run_summary(ds))
    return 0


def _print_v2(path, ds, table) -> None:
    """The ``validate`` summary of a format 2 dataset: parts, channels, inputs, segments."""
    from .data.reference import frame_text
    from .data.views import split_segments

    meta = ds.metadata
    # everything that can still refuse the dataset first: "valid" is printed only for a dataset that is
    seg = split_segments(ds) if any(r.condition is None for r in meta.runs.values()) else ds
    print(f"{path}: valid {meta.format} dataset, machine {meta.machine.name}, parts: {', '.join(meta.parts or [])}")
    print(f"  {len(ds.process)} process rows, {len(ds.errors)} error readings; operating inputs: "
          f"{', '.join(meta.operating_inputs()) or 'none'}; sensors: {', '.join(ds.sensor_columns) or 'none'}")  # fmt: skip
    for name, ch in meta.error_channels().items():
        print(f"  channel {name}: {ch.kind}, {ch.direction}, at {ch.location} ({'µrad' if ch.unit == 'urad' else 'µm'})")
    print(f"  thermal error counted from: {meta.reference_mode().mode}"
          + (f" at {meta.reference_mode().t_s:g} s" if meta.reference_mode().t_s is not None else "")
          + f"; models are scored on {frame_text(meta)}")  # fmt: skip
    if "direction" in ds.errors.columns:
        print("  bidirectional readings: thermal error per direction; the reversal value: thermbench iso230")
    print(f"\nruns  ->  {Path(path).resolve()}")
    print(table.to_string(index=False, float_format=lambda v: f"{v:.1f}"))
    if seg is not ds:
        derived = [r for r in seg.metadata.runs if r not in meta.runs]
        if derived:
            print("\nderived segments (data/segments.py; usable as run ids in train=, dataset.states, ...):")
            for r in derived:
                print(f"  {r}: {seg.metadata.runs[r].notes}")


def cmd_import(mapping: str, out: str, file_format: str, force: bool) -> int:
    import time

    from .data.importer import import_dataset
    from .data.reference import run_summary

    t0 = time.perf_counter()
    ds = import_dataset(mapping, out, file_format=file_format, force=force,
                        progress=lambda msg: print(f"  {msg}", file=sys.stderr, flush=True))
    print(f"imported {mapping} -> {Path(out).resolve()} in {time.perf_counter() - t0:.1f} s")
    for note in getattr(ds, "import_notes", []):
        print(f"  {note}")
    _print_v2(out, ds, run_summary(ds))
    return 0


def cmd_iso230(data_dir: str, out: str, force: bool) -> int:
    from .iso230.report import iso230_report

    figs = iso230_report(data_dir, out, force=force)
    for run, res in figs["runs"].items():
        for ch, e in res["channels"].items():
            if e["kind"] == "fixed_point":
                a = next(r for r in e["drift"] if r["block"] == "all")
                print(f"  {run} {ch}: max drift {a['max_from_reference_um']} µm at {a['t_max_from_reference_s']} s")
            else:
                b = e.get("iso230_2_run", {}).get("B_um")
                extra = f", reversal B {b} µm" if b is not None else ""
                print(f"  {run} {ch}: max |thermal error| {e['max_thermal_um']} µm{extra}")
    print(f"  -> {Path(out).resolve() / 'report.md'}")
    return 0


def cmd_classify(stroke_mm: float, start_mm: float, end_mm: float, feed_mm_min: float, classifier: str) -> int:
    from hydra.utils import instantiate

    from .models.classify import ProximityNaiveBayes
    from .models.classify_one import classify_motion, format_classification
    from .config import ConfigError
    from .experiment import group_option

    clf = instantiate(group_option("classifier", classifier), _convert_="all")
    if not (isinstance(clf, ProximityNaiveBayes) and clf.conditions):
        raise ConfigError(
            f"--classifier {classifier}: needs a proximity classifier with preset conditions "
            "(conf/classifier/seed002.yaml); the others learn their conditions from training runs"
        )
    label, table = classify_motion(stroke_mm, start_mm, end_mm, feed_mm_min, classifier=clf)
    print(format_classification(label, table))
    return 0


def cmd_diagnose(data_dir: str, out_dir: str, base: str | None, max_effects: int | None, overrides: list[str],
                 force: bool = False, channel: str | None = None) -> int:  # fmt: skip
    from omegaconf import OmegaConf

    from .config import compose_checked

    # paths and lists go in after composition: no Hydra quoting of arbitrary paths
    cfg = compose_checked("diagnose", overrides, fill={"data_dir": data_dir, "out_dir": out_dir})
    from .discrepancy import diagnose

    if base is not None:
        OmegaConf.update(cfg, "base", [b.strip() for b in base.split(",") if b.strip()])
    if max_effects is not None:
        OmegaConf.update(cfg, "max_effects", max_effects)
    if force:
        OmegaConf.update(cfg, "force", True)
    if channel is not None:
        OmegaConf.update(cfg, "channel", channel)
    diagnose(cfg)
    return 0


def cmd_replay(model_dir: str, data_dir: str, run: str, out: str | None, force: bool = False,
               channel: str | None = None, probes: str | None = None) -> int:
    from .export.replay import format_replay, read_probes, replay_run, write_replay
    from .outputs import check_output_dir

    out_dir = Path(out) if out else Path("replays") / f"{Path(model_dir).name}__{run}"
    check_output_dir(out_dir, "replay", force=force)  # refused before the replay runs
    table = read_probes(Path(probes)) if probes else None
    res = replay_run(Path(model_dir), Path(data_dir), run, channel=channel, probes=table)
    write_replay(res, out_dir, force=force)
    print(format_replay(res["figures"]))
    print(f"  -> {out_dir.resolve()}")
    return 0


def cmd_precompensate(args) -> int:
    from .precompensate import PrecompError, format_summary, run_precompensate

    if args.model is not None and args.models is not None:
        raise PrecompError("precompensate: --model and --models together; expected one of them (--model: one axis, "
                           "--models: each axis its own model)")  # fmt: skip
    if args.model is None and args.models is None:
        raise PrecompError("precompensate: no model; expected one of --model MODEL.joblib (one axis) or --models "
                           "AXES.yaml (each axis its own model)")  # fmt: skip
    if args.models is not None:
        from .precompensate.axes import format_axes_summary, run_precompensate_axes

        if args.axis is not None:
            raise PrecompError(f"precompensate: --axis with --models: the axes are the keys of {args.models} (X: ..., "
                               "Y: ..., Z: ...)")  # fmt: skip
        given = [o for o, v in (("--start-mm", args.start_mm), ("--work-offset", args.work_offset),
                                ("--dataset", args.dataset)) if v is not None]  # fmt: skip
        if given:
            raise PrecompError(f"precompensate: {', '.join(given)} with --models: give them per axis in {args.models} "
                               "(X: {model: ..., dataset: ..., start_mm: ..., work_offset_mm: ...})")  # fmt: skip
        res = run_precompensate_axes(args.program, args.models, args.out, verify=args.verify, rapid_mm_min=args.rapid,
                                     sample_s=args.sample, ambient_C=args.ambient, decimals=args.decimals,
                                     flatten=args.flatten, tool_table=args.tool_table, ini=args.ini)  # fmt: skip
        print(format_axes_summary(res))
        return 0
    res = run_precompensate(args.program, args.model, args.out, dataset=args.dataset,
                            truth="auto" if args.verify else None, axis=args.axis or "X", rapid_mm_min=args.rapid,
                            sample_s=args.sample, start_mm=args.start_mm, work_offset_mm=args.work_offset or 0.0,
                            ambient_C=args.ambient, decimals=args.decimals, flatten=args.flatten,
                            tool_table=args.tool_table, ini=args.ini)  # fmt: skip
    print(format_summary(res))
    return 0


def _quiet_asyncua() -> None:
    import logging

    # its chatter (session timeouts, tracebacks of refused connections): our one-line errors say what went wrong
    logging.getLogger("asyncua").setLevel(logging.CRITICAL)


def _compose(name: str, overrides: list[str], **paths):
    from omegaconf import OmegaConf

    from .config import compose_checked

    # paths and URLs go in after composition: no Hydra quoting
    cfg = compose_checked(name, overrides, fill={k: v for k, v in paths.items() if v is not None})
    return OmegaConf.to_container(cfg, resolve=True)


def _require_opcua(command: str) -> None:
    """The OPC UA commands need the ``opcua`` extra (asyncua): one line naming it if missing."""
    from .errors import require

    require("asyncua", command)


def cmd_compensator(model_dir: str, endpoint: str, nodes: str, overrides: list[str]) -> int:
    import asyncio

    cfg = _compose("compensator", overrides)  # first: a mistake is reported before asyncua loads
    _require_opcua("thermbench compensator")
    from .compensator.client import Compensator, format_summary

    _quiet_asyncua()
    comp = Compensator(Path(model_dir), endpoint, Path(nodes), cfg, say=lambda line: print(line, flush=True))

    async def run() -> dict:
        import signal

        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):  # Ctrl-C ends the loop after its cycle, with the summary
            loop.add_signal_handler(sig, comp.stop, "interrupted")
        return await comp.run()

    summary = asyncio.run(run())
    print(format_summary(summary))
    return 130 if summary["ended"] == "interrupted" else 0


def cmd_station(path: str, overrides: list[str]) -> int:
    import asyncio

    import yaml

    from .compensator.station import StationError, Station, format_summary, load_station

    spec = load_station(path)
    for o in overrides:  # top-level keys of the station file: period_s=0.05 duration_s=60
        key, eq, value = o.partition("=")
        if not eq or key not in ("period_s", "duration_s", "max_cycles", "status_every_s", "log_dir", "timeout_s"):
            raise StationError(f"override {o!r}: expected KEY=VALUE with KEY one of period_s, duration_s, max_cycles, "
                               "status_every_s, log_dir, timeout_s")  # fmt: skip
        spec[key] = yaml.safe_load(value)
    _require_opcua("thermbench station")
    _quiet_asyncua()
    station = Station(spec, say=lambda line: print(line, flush=True))

    async def run() -> dict:
        import signal

        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, station.stop, "interrupted")
        return await station.run()

    print(format_summary(asyncio.run(run())))
    return 0


def cmd_sim_cnc(endpoint: str | None, overrides: list[str]) -> int:
    import asyncio

    cfg = _compose("sim_cnc", overrides, endpoint=endpoint)  # first: a mistake is reported before asyncua loads
    _require_opcua("thermbench sim-cnc")
    from .compensator.simcnc import build_machine, format_figures, serve

    _quiet_asyncua()
    machine = build_machine(cfg)
    print(f"sim-cnc: run {machine.run}, {len(machine.samples)} samples at {cfg['speed']:g}x real time on {cfg['endpoint']}"
          + (" (starts when a client first reads it)" if cfg["start"] == "on_compensator" else ""), flush=True)  # fmt: skip
    print(format_figures(asyncio.run(serve(cfg, machine))))
    return 0


def cmd_certs(out_dir: str, days: int, host: str | None) -> int:
    _require_opcua("thermbench certs")
    from .compensator.certs import make_certificates

    for role, path in make_certificates(out_dir, days=days, host=host).items():
        print(f"{role:20s} {path}")
    return 0


def cmd_linuxcnc(what: str, model_dir: str | None, overrides: list[str]) -> int:
    """``thermbench linuxcnc component|plant|sim``: thermbench/linuxcnc/."""
    say = lambda line: print(line, flush=True)  # noqa: E731
    if what == "component":
        from .linuxcnc.component import HalCompensator

        HalCompensator(Path(model_dir), _compose("linuxcnc_component", overrides), say=say).run()
        return 0
    if what == "plant":
        from .linuxcnc.plant import ThermalPlant

        f = ThermalPlant(_compose("linuxcnc_plant", overrides)).run()
        say(f"tbplant: {f.get('samples', 0)} process samples written")
        return 0
    from .linuxcnc.sim import run_sim
    from .linuxcnc.verify import format_figures

    cfg = _compose("linuxcnc_sim", overrides)
    print(format_figures(run_sim(Path(model_dir), cfg, say=say)))
    print(f"  -> {Path(cfg['out_dir']).resolve()}")
    return 0


HYDRA_JOBS = ("train", "evaluate", "benchmark", "export")


class _Parser(argparse.ArgumentParser):
    """argparse, with a usage mistake in one line (the usage is one --help away)."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def _number(lowest: float | None = None, integer: bool = False):
    """An argparse type: a finite number (an integer), >= ``lowest`` if given."""

    def parse(text: str):
        try:
            value = int(text) if integer else float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {'an integer' if integer else 'a number'}, got {text!r}") from None
        if not math.isfinite(value) or (lowest is not None and value < lowest):
            bound = f" >= {lowest:g}" if lowest is not None else ""
            raise argparse.ArgumentTypeError(f"expected a finite {'integer' if integer else 'number'}{bound}, got {text!r}")
        return value

    return parse


def main(argv: list[str] | None = None) -> int:
    """``thermbench ...``: the exit code. 2: a user mistake, reported in one line on stderr
    (:func:`thermbench.errors.user_errors`); any other exception is a bug and keeps its
    traceback. 141: the reader of stdout went away (``thermbench ... | head``), quietly."""
    from .errors import BROKEN_PIPE_EXIT, GuardedStdout, StdoutClosed, stdout_closed

    stdout = sys.stdout
    sys.stdout = GuardedStdout(stdout)
    saved_format = warnings.formatwarning
    warnings.formatwarning = _format_warning
    try:  # SIGTERM unwinds like Ctrl-C: staging directories and temporary files are removed
        saved_term = signal.signal(signal.SIGTERM, _terminated)
    except ValueError:  # not the main thread
        saved_term = None
    try:
        code = _main(argv)
        sys.stdout.flush()  # now, while a closed pipe is still ours to handle
        return code
    except StdoutClosed:
        return BROKEN_PIPE_EXIT
    except BrokenPipeError:  # written around the guard (a stream kept from before)
        stdout_closed(stdout)
        return BROKEN_PIPE_EXIT
    finally:
        sys.stdout = stdout
        warnings.formatwarning = saved_format
        if saved_term is not None:
            signal.signal(signal.SIGTERM, saved_term)


def _format_warning(message, category, filename, lineno, line=None) -> str:
    """thermbench's own warnings (a dataset column ignored, a replay on another machine) as one line
    ``thermbench: warning: ...``; anybody else's keep Python's form, with the file and line."""
    if category.__module__.startswith("thermbench."):
        return f"thermbench: warning: {message}\n"
    return _PY_FORMAT(message, category, filename, lineno, line)


_PY_FORMAT = warnings.formatwarning


def _terminated(signum, frame) -> None:
    raise SystemExit(128 + signum)


def _main(argv: list[str] | None) -> int:
    from .errors import report, user_errors

    argv = list(sys.argv[1:] if argv is None else argv)
    if argv and argv[0] in HYDRA_JOBS:
        from .app import run

        return run(argv[0], argv[1:])

    parser = _Parser(
        prog="thermbench",
        description="Thermal error modelling and compensation for CNC machine tools: ball-screw feed axes and spindles.",
        epilog="Hydra jobs: thermbench {train,evaluate,benchmark,export} [overrides] [-m] [--help]",
    )
    parser.add_argument("--version", action="version", version=f"thermbench {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)
    p_sim = sub.add_parser("simulate", help="simulate a dataset (Hydra overrides, e.g. machine=seed002_vmc655h_x clean=true)")
    p_sim.add_argument("overrides", nargs="*", help="Hydra overrides key=value")
    p_val = sub.add_parser("validate", help="validate a dataset directory against the contract")
    p_val.add_argument("data_dir")
    p_imp = sub.add_parser("import", help="bring a lab's files (CSV, Excel, Parquet) in as a dataset, "
                           "described by one YAML mapping file (docs/import.md)")
    p_imp.add_argument("mapping", help="the mapping file (format: thermbench-import/1)")
    p_imp.add_argument("--out", required=True, help="the dataset directory to write")
    p_imp.add_argument("--format", dest="file_format", choices=("csv", "parquet"), default="parquet",
                       help="table files of the dataset (default parquet)")
    p_imp.add_argument("--force", action="store_true", help="also write into a directory holding other files "
                       "(never over them)")
    p_iso = sub.add_parser("iso230", help="ISO 230-2 positioning and ISO 230-3 thermal figures of a dataset")
    p_iso.add_argument("data_dir", help="dataset directory")
    p_iso.add_argument("--out", required=True, help="output directory (report.md, figures.json, figures)")
    p_iso.add_argument("--force", action="store_true", help="also write into a directory holding other files "
                       "(never over them)")
    p_cls = sub.add_parser("classify", help="seed 002 naive-Bayes motion-condition classifier (eq. 15-19)")
    p_cls.add_argument("--stroke", type=_number(0), required=True, help="working stroke A, mm")
    p_cls.add_argument("--start", type=_number(), required=True, help="stroke start P_start, mm")
    p_cls.add_argument("--end", type=_number(), required=True, help="stroke end P_end, mm")
    p_cls.add_argument("--feed", type=_number(0), required=True, help="feed C, mm/min")
    p_cls.add_argument("--classifier", default="seed002", help="conf/classifier option (default: seed002, Table 5)")
    p_dia = sub.add_parser("diagnose", help="discrepancy workflow: where the physics model and the data disagree, "
                           "which effect is missing (conf/diagnose.yaml); a screw axis or a spindle test")  # fmt: skip
    p_dia.add_argument("data_dir", help="dataset directory in the contract format, or a dataset option (fl_thermal)")
    p_dia.add_argument("--channel", default=None, help="the error channel of a dataset with several (ch3)")
    p_dia.add_argument("--out", required=True, help="output directory (diagnosis.json, report.md, figures)")
    p_dia.add_argument("--force", action="store_true", help="also write into a directory holding other files "
                       "(never over them; never into a dataset)")  # fmt: skip
    p_dia.add_argument("--base", default=None, help="canonical effects already in the model, comma-separated")
    p_dia.add_argument("--max-effects", type=int, default=None, help="add at most K effects (default 3)")
    p_dia.add_argument("overrides", nargs="*", help="Hydra overrides of conf/diagnose.yaml, e.g. track=false")
    p_rep = sub.add_parser("replay", help="drive an exported model in the C runtime with a run's process log; "
                           "error before/after compensation")  # fmt: skip
    p_rep.add_argument("model_dir", help="a directory written by thermbench export (manifest.json)")
    p_rep.add_argument("data_dir", help="dataset directory in the contract format")
    p_rep.add_argument("--run", required=True, help="run id to replay (or a derived segment of a format 2 run)")
    p_rep.add_argument("--channel", default=None, help="format 2: the error channel the model predicts "
                       "(default: the one it was trained on, from its manifest)")
    p_rep.add_argument("--out", default=None, help="output directory (default replays/<model>__<run>)")
    p_rep.add_argument("--probes", default=None, help="CSV of probe readings (t_s, measured_um[, axis_mm]): they correct "
                       "the model as the compensator's probe input does (docs/intervals.md)")  # fmt: skip
    p_rep.add_argument("--force", action="store_true", help="also write into a directory holding other files "
                       "(never over them; never into a dataset)")  # fmt: skip
    p_pre = sub.add_parser("precompensate", help="seed 003: revise a part program before machining (no sensors)")
    p_pre.add_argument("program", help="G-code program (mm, G21)")
    p_pre.add_argument("--model", default=None, help="fitted physics or AR model (.joblib) of the one axis --axis, e.g. "
                       "models/benchmark/seed000_x__physics__global.joblib")  # fmt: skip
    p_pre.add_argument("--models", default=None, help="YAML mapping each axis to its model (X: m.joblib, Y: {model: ..., "
                       "dataset: ..., start_mm: ..., work_offset_mm: ...}): every axis revised by its own, on one time line "
                       "(docs/precompensate.md)")  # fmt: skip
    p_pre.add_argument("--out", required=True, help="rewritten program (written atomically)")
    p_pre.add_argument("--dataset", default=None, help="dataset the model was trained on: benchmark name or directory "
                       "(default: from a benchmark model file name <dataset>__<family>__<approach>.joblib)")  # fmt: skip
    p_pre.add_argument("--axis", default=None, help="the axis --model revises (default X)")
    p_pre.add_argument("--rapid", type=float, default=10000.0, help="G0 feed, mm/min")
    p_pre.add_argument("--sample", type=float, default=1.0, help="planned process log step, s (<= 1)")
    p_pre.add_argument("--start-mm", type=float, default=None, help="axis position before the first block")
    p_pre.add_argument("--work-offset", type=float, default=None, help="axis position = program coordinate + this, mm "
                       "(default 0)")
    p_pre.add_argument("--ambient", type=float, default=20.0, help="ambient held constant for a physics model, °C")
    p_pre.add_argument("--decimals", type=int, default=4)
    p_pre.add_argument("--flatten", choices=["auto", "always", "never"], default="auto",
                       help="expand parameters, loops, subroutines and arcs with LinuxCNC's rs274 (auto: when the reader "
                       "cannot follow the program and rs274 is installed; always: arcs too, as compensated chords); "
                       "the output is then the flattened program")  # fmt: skip
    p_pre.add_argument("--tool-table", default=None, help="LinuxCNC tool table for rs274 (default: tools 1-99, no offsets)")
    p_pre.add_argument("--ini", default=None, help="the machine's LinuxCNC INI for rs274: subroutine paths, the work "
                       "offsets of its PARAMETER_FILE (a program that switches to G55 ... needs them)")  # fmt: skip
    p_pre.add_argument("--verify", action="store_true", help="replay both programs in the simulator that made --dataset")
    p_cmp = sub.add_parser("compensator", help="OPC UA compensator: read the machine, run the exported model in the "
                           "C runtime, write the compensation (conf/compensator.yaml)")  # fmt: skip
    p_cmp.add_argument("model_dir", help="a directory written by thermbench export (manifest.json)")
    p_cmp.add_argument("--endpoint", required=True, help="the machine's OPC UA endpoint, opc.tcp://HOST:PORT[/path]")
    p_cmp.add_argument("--nodes", required=True, help="nodes.yaml: node ids of the inputs and outputs")
    p_cmp.add_argument("overrides", nargs="*", help="overrides of conf/compensator.yaml, e.g. period_s=0.1 output=line")
    p_sta = sub.add_parser("station", help="one compensator for several axes and spindle channels over several OPC UA "
                           "endpoints (a station file: thermbench/compensator/station.py)")  # fmt: skip
    p_sta.add_argument("station", help="the station file (YAML: endpoints, channels)")
    p_sta.add_argument("overrides", nargs="*", help="period_s=..., duration_s=..., max_cycles=..., log_dir=...")
    p_sim_cnc = sub.add_parser("sim-cnc", help="a simulated CNC axis behind an OPC UA server (conf/sim_cnc.yaml)")
    p_sim_cnc.add_argument("--endpoint", default=None, help="endpoint to serve (default from conf/sim_cnc.yaml)")
    p_sim_cnc.add_argument("overrides", nargs="*", help="overrides, e.g. benchmark=seed001_vmc_x run=valid1 speed=100")
    p_certs = sub.add_parser("certs", help="self-signed OPC UA application certificates (server and client)")
    p_certs.add_argument("out_dir")
    p_certs.add_argument("--days", type=_number(1, integer=True), default=365, help="validity, days (>= 1)")
    p_certs.add_argument("--host", default=None, help="host name in the certificates (default: this host's)")
    p_lcnc = sub.add_parser("linuxcnc", help="LinuxCNC: the compensator as a HAL component writing the external offsets "
                            "(component), a simulated thermal plant (plant), a headless closed-loop run (sim)")  # fmt: skip
    p_lcnc.add_argument("what", choices=["component", "plant", "sim"])
    p_lcnc.add_argument("model_dir", nargs="?", default=None, help="an exported model (component, sim)")
    p_lcnc.add_argument("overrides", nargs="*", help="overrides of conf/linuxcnc_<what>.yaml")
    commands = [*sub.choices, *HYDRA_JOBS]
    if argv and not argv[0].startswith("-") and argv[0] not in commands:
        guess = difflib.get_close_matches(argv[0], commands, n=1)
        hint = f"; did you mean '{guess[0]}'?" if guess else ";"
        parser.error(f"unknown command '{argv[0]}'{hint} the commands: {', '.join(commands)}")
    # overrides may follow the options (argparse matches positionals in one chunk)
    args, extra = parser.parse_known_args(argv)
    if extra and (args.command not in ("diagnose", "compensator", "sim-cnc", "linuxcnc", "station") or any(e.startswith("-") for e in extra)):
        parser.error(f"unrecognized arguments: {' '.join(extra)}")
    try:
        if args.command == "diagnose":
            return cmd_diagnose(args.data_dir, args.out, args.base, args.max_effects, [*args.overrides, *extra], args.force,
                                args.channel)
        if args.command == "compensator":
            return cmd_compensator(args.model_dir, args.endpoint, args.nodes, [*args.overrides, *extra])
        if args.command == "sim-cnc":
            return cmd_sim_cnc(args.endpoint, [*args.overrides, *extra])
        if args.command == "certs":
            return cmd_certs(args.out_dir, args.days, args.host)
        if args.command == "station":
            return cmd_station(args.station, [*args.overrides, *extra])
        if args.command == "linuxcnc":
            overrides = [*args.overrides, *extra]
            if args.what == "plant" and args.model_dir is not None:  # the plant takes no model: that was an override
                overrides.insert(0, args.model_dir)
                args.model_dir = None
            if args.what != "plant" and (args.model_dir is None or "=" in args.model_dir):
                parser.error(f"linuxcnc {args.what}: the exported model directory comes first (thermbench export writes it)")
            return cmd_linuxcnc(args.what, args.model_dir, overrides)
        if args.command == "simulate":
            return cmd_simulate(args.overrides)
        if args.command == "replay":
            return cmd_replay(args.model_dir, args.data_dir, args.run, args.out, args.force, args.channel, args.probes)
        if args.command == "precompensate":
            return cmd_precompensate(args)
        if args.command == "iso230":
            return cmd_iso230(args.data_dir, args.out, args.force)
        if args.command == "import":
            return cmd_import(args.mapping, args.out, args.file_format, args.force)
        if args.command == "classify":
            return cmd_classify(args.stroke, args.start, args.end, args.feed, args.classifier)
        return cmd_validate(args.data_dir)
    except user_errors() as exc:  # user mistakes, and the C runtime's refusals; anything else is a bug: traceback
        return report("thermbench", exc)
    except KeyboardInterrupt:
        print(f"thermbench {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
