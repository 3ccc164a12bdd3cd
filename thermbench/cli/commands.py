"""Each ``thermbench`` command (:mod:`thermbench.cli`) as a function of its arguments: a thin call into
the importable function that does the work, its summary printed; the exit code.
"""

from __future__ import annotations

import sys
from pathlib import Path

def _print_summary(title: str, path: Path, table) -> None:
    print(f"\n{title}  ->  {path}")
    show = table[["run_id", "duration_h", "stroke_mm", "start_mm", "end_mm", "feed_mm_min", "max_thermal_error_um"]]
    print(show.to_string(index=False, float_format=lambda v: f"{v:.1f}"))


def cmd_simulate(overrides: list[str]) -> int:
    from ..config import ConfigError, compose_checked

    cfg = compose_checked("simulate", overrides)  # first: a mistake is reported before the simulator loads
    from ..bench import datasets
    from ..data.io import load_dataset, save_dataset
    from ..data.reference import run_summary
    from ..sim.scenario import simulate_dataset

    if cfg.get("suite") == "benchmark":
        from ..outputs import check_output_dir

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
    from ..outputs import check_output_dir

    force = cfg.get("force", False)
    if not isinstance(force, bool):
        raise ConfigError(f"config key 'force': expected true or false, got {force!r}")
    check_output_dir(Path(str(cfg.out_dir)), "dataset", force=force, force_option="force=true")  # before simulating
    ds, _ = simulate_dataset(cfg)
    path = save_dataset(ds, Path(str(cfg.out_dir)), file_format=str(cfg.file_format), force=force)
    _print_summary(f"[{cfg.machine.name} / {cfg.protocol.name}] simulated", path.resolve(), run_summary(load_dataset(path)))
    return 0


def cmd_validate(path: str) -> int:
    from ..data.io import load_dataset
    from ..data.reference import run_summary

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
    from ..data.reference import frame_text
    from ..data.views import split_segments

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

    from ..data.importer import import_dataset
    from ..data.reference import run_summary

    t0 = time.perf_counter()
    ds = import_dataset(mapping, out, file_format=file_format, force=force,
                        progress=lambda msg: print(f"  {msg}", file=sys.stderr, flush=True))
    print(f"imported {mapping} -> {Path(out).resolve()} in {time.perf_counter() - t0:.1f} s")
    for note in getattr(ds, "import_notes", []):
        print(f"  {note}")
    _print_v2(out, ds, run_summary(ds))
    return 0


def cmd_iso230(data_dir: str, out: str, force: bool) -> int:
    from ..iso230.report import iso230_report

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

    from ..models.classify import ProximityNaiveBayes
    from ..models.classify_one import classify_motion, format_classification
    from ..config import ConfigError
    from ..experiment import group_option

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

    from ..config import compose_checked

    # paths and lists go in after composition: no Hydra quoting of arbitrary paths
    cfg = compose_checked("diagnose", overrides, fill={"data_dir": data_dir, "out_dir": out_dir})
    from ..discrepancy import diagnose

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
    from ..export.replay import format_replay, read_probes, replay_run, write_replay
    from ..outputs import check_output_dir

    out_dir = Path(out) if out else Path("replays") / f"{Path(model_dir).name}__{run}"
    check_output_dir(out_dir, "replay", force=force)  # refused before the replay runs
    table = read_probes(Path(probes)) if probes else None
    res = replay_run(Path(model_dir), Path(data_dir), run, channel=channel, probes=table)
    write_replay(res, out_dir, force=force)
    print(format_replay(res["figures"]))
    print(f"  -> {out_dir.resolve()}")
    return 0


def cmd_precompensate(args) -> int:
    from ..precompensate import PrecompError, format_summary, run_precompensate

    if args.model is not None and args.models is not None:
        raise PrecompError("precompensate: --model and --models together; expected one of them (--model: one axis, "
                           "--models: each axis its own model)")  # fmt: skip
    if args.model is None and args.models is None:
        raise PrecompError("precompensate: no model; expected one of --model MODEL.joblib (one axis) or --models "
                           "AXES.yaml (each axis its own model)")  # fmt: skip
    if args.models is not None:
        from ..precompensate.axes import format_axes_summary, run_precompensate_axes

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

    from ..config import compose_checked

    # paths and URLs go in after composition: no Hydra quoting
    cfg = compose_checked(name, overrides, fill={k: v for k, v in paths.items() if v is not None})
    return OmegaConf.to_container(cfg, resolve=True)


def _require_opcua(command: str) -> None:
    """The OPC UA commands need the ``opcua`` extra (asyncua): one line naming it if missing."""
    from ..errors import require

    require("asyncua", command)


def cmd_compensator(model_dir: str, endpoint: str, nodes: str, overrides: list[str]) -> int:
    import asyncio

    cfg = _compose("compensator", overrides)  # first: a mistake is reported before asyncua loads
    _require_opcua("thermbench compensator")
    from ..compensator.client import Compensator, format_summary

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

    from ..compensator.station import StationError, Station, format_summary, load_station

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
    from ..compensator.simcnc import build_machine, format_figures, serve

    _quiet_asyncua()
    machine = build_machine(cfg)
    print(f"sim-cnc: run {machine.run}, {len(machine.samples)} samples at {cfg['speed']:g}x real time on {cfg['endpoint']}"
          + (" (starts when a client first reads it)" if cfg["start"] == "on_compensator" else ""), flush=True)  # fmt: skip
    print(format_figures(asyncio.run(serve(cfg, machine))))
    return 0


def cmd_certs(out_dir: str, days: int, host: str | None) -> int:
    _require_opcua("thermbench certs")
    from ..compensator.certs import make_certificates

    for role, path in make_certificates(out_dir, days=days, host=host).items():
        print(f"{role:20s} {path}")
    return 0


def cmd_linuxcnc(what: str, model_dir: str | None, overrides: list[str]) -> int:
    """``thermbench linuxcnc component|plant|sim``: thermbench/linuxcnc/."""
    say = lambda line: print(line, flush=True)  # noqa: E731
    if what == "component":
        from ..linuxcnc.component import HalCompensator

        HalCompensator(Path(model_dir), _compose("linuxcnc_component", overrides), say=say).run()
        return 0
    if what == "plant":
        from ..linuxcnc.plant import ThermalPlant

        f = ThermalPlant(_compose("linuxcnc_plant", overrides)).run()
        say(f"tbplant: {f.get('samples', 0)} process samples written")
        return 0
    from ..linuxcnc.sim import run_sim
    from ..linuxcnc.verify import format_figures

    cfg = _compose("linuxcnc_sim", overrides)
    print(format_figures(run_sim(Path(model_dir), cfg, say=say)))
    print(f"  -> {Path(cfg['out_dir']).resolve()}")
    return 0
