"""``thermbench replay MODEL_DIR DATA_DIR --run ID``: the exported model in the C runtime,
driven by a run's process log at the control cycle, error before and after compensation.

The C runtime (``tb_replay``) is stepped with every process sample (one control
cycle); a per-condition bank's classifier switches models online from the motion
window (seed 002 §2.4-2.5). The runtime is asked for the compensation at every
sample (at the axis position of that moment, what the compensator sends to the
CNC) and at every interferometer reading. Before = the measured thermal error
(reading minus the cold reference, as seed 000 §5 and seed 002 §3 report it);
after = reading minus the runtime's predicted positioning error: what the axis
would show with that compensation applied (:mod:`thermbench.bench.metrics`).

Outputs, written atomically to ``--out``: ``replay.json`` (figures), ``readings.csv``,
``compensation.csv`` and two figures: the errors at the measuring points before and
after over time (seed 000 Fig. 13 analogue) and per measuring cycle the max |error|
before/after with the condition the bank had chosen (seed 002 Fig. 22 analogue).
"""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np
import pandas as pd

from ..data.io import load_dataset
from ..data.reference import frame_text, thermal_errors
from ..bench.metrics import cycle_curves, residual_metrics
from ..outputs import output_dir
from .directory import read_manifest, replay_dir
from .encoding import ExportError


class MachineMismatchWarning(UserWarning):
    """The dataset replayed is of another machine than the one the model was trained on."""


def _machine(machine) -> tuple[str, str | None] | None:
    """(name, axis) of a machine as a manifest or a dataset's metadata records it (a name, or a
    mapping / object with ``name`` and ``axis``); None when it names none."""
    if isinstance(machine, str):
        return (machine, None) if machine else None
    get = machine.get if isinstance(machine, dict) else (lambda key: getattr(machine, key, None))
    name, axis = get("name"), get("axis")
    if not isinstance(name, str) or not name:
        return None
    return name, (str(axis) if axis else None)


def _machine_text(machine: tuple[str, str | None]) -> str:
    name, axis = machine
    return f"{name!r} (axis {axis})" if axis else repr(name)


def model_machine(man: dict, model_dir: Path) -> tuple[tuple[str, str | None], str] | None:
    """((name, axis), where it is recorded) of the machine the model was trained on:
    ``training.machine`` in its manifest (written by the export), else, for a model exported before
    that was recorded, the ``machine`` of its training dataset (``training.dataset``, read when that
    directory is still there); None when neither says."""
    training = man.get("training") if isinstance(man.get("training"), dict) else {}
    machine = _machine(training.get("machine"))
    if machine is not None:
        return machine, f"{Path(model_dir) / 'manifest.json'}, training.machine"
    data = training.get("dataset")
    if isinstance(data, str) and data and (Path(data) / "metadata.yaml").is_file():
        from ..data.io import load_metadata

        try:
            machine = _machine(load_metadata(Path(data)).machine)
        except ValueError:  # the training dataset changed since (a DatasetError): nothing to compare with
            return None
        if machine is not None:
            return machine, f"its training dataset {Path(data) / 'metadata.yaml'}"
    return None


def check_machine(man: dict, model_dir: Path, ds, data_dir: Path) -> str | None:
    """Warn (:class:`MachineMismatchWarning`, one line naming both machines) when the dataset at
    ``data_dir`` is of another machine (or axis) than the one the model was trained on; returns
    the message (None: the same machine, or the model or the dataset records none)."""
    recorded = model_machine(man, model_dir)
    theirs = _machine(ds.metadata.machine)
    if recorded is None or theirs is None:
        return None
    mine, where = recorded
    if mine[0] == theirs[0] and (mine[1] is None or theirs[1] is None or mine[1] == theirs[1]):
        return None
    message = (f"model {model_dir} was trained on machine {_machine_text(mine)} ({where}), but "
               f"{Path(data_dir) / 'metadata.yaml'} is of machine {_machine_text(theirs)}: the compensation is "
               "replayed on a machine the model was not fitted to")  # fmt: skip
    warnings.warn(message, MachineMismatchWarning, stacklevel=3)
    return message


def replay_view(ds, man: dict, run: str, channel: str | None, data_dir: Path):
    """A format 2 dataset as the model saw it: the error channel it was trained on (``--channel``,
    else the one in its manifest, else the only one) and, when ``run`` names a derived
    segment, the run split into its segments (with the log before each, when the model was
    trained that way: ``training.history`` in its manifest)."""
    from ..bench.splits import model_view

    channels = sorted(ds.metadata.error_channels())
    channel = channel or man.get("training", {}).get("channel")
    if channel is None:
        if len(channels) > 1:
            raise ExportError(f"--channel: {data_dir} has {len(channels)} error channels {channels}; name the one "
                              "the model predicts")  # fmt: skip
        channel = channels[0] if channels else None
    if channel is not None and channel not in channels:
        raise ExportError(f"--channel {channel!r}: not a channel of {data_dir}; its channels: {channels}")
    if run in ds.run_ids:  # a whole run
        return model_view(ds, channel, segments=False)
    # a derived segment: split as the model was trained (with the log before it: training.history)
    history = channel is not None and bool(man.get("training", {}).get("history"))
    view = model_view(ds, channel, segments=True, history=history)
    if history and run not in view.run_ids:  # not a segment of the history split: try the plain one
        view = model_view(ds, channel, segments=True)
    return view if run in view.run_ids else model_view(ds, channel, segments=False)  # no such run: the runs as they are


def read_probes(path: Path) -> pd.DataFrame:
    """A probe file for ``thermbench replay --probes``: CSV with a header, columns ``t_s`` (the run's
    time of the reading, s) and ``measured_um`` (the measured error, the model's sign), optionally
    ``axis_mm`` (where it was taken; default: the axis position then). Times nondecreasing."""
    path = Path(path)
    try:
        df = pd.read_csv(path)
    except FileNotFoundError:
        raise ExportError(f"--probes {path}: no such file") from None
    except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError) as exc:
        raise ExportError(f"--probes {path}: not a CSV file with a header ({str(exc).splitlines()[0]})") from None
    missing = [c for c in ("t_s", "measured_um") if c not in df.columns]
    if missing:
        raise ExportError(f"--probes {path}: no column {missing[0]!r}; expected t_s, measured_um and optionally axis_mm, "
                          f"got {list(df.columns)}")  # fmt: skip
    cols = [c for c in ("t_s", "measured_um", "axis_mm") if c in df.columns]
    for c in cols:
        v = pd.to_numeric(df[c], errors="coerce")
        bad = np.flatnonzero(~np.isfinite(v.to_numpy(dtype=float)))
        if bad.size:
            raise ExportError(f"--probes {path}: column {c!r}, row {bad[0] + 2}: expected a finite number, got {df[c].iloc[bad[0]]!r}")
        df[c] = v.astype(float)
    back = np.flatnonzero(np.diff(df["t_s"].to_numpy()) < 0)
    if back.size:
        raise ExportError(f"--probes {path}: column 't_s', row {back[0] + 3}: times go back "
                          f"({df['t_s'].iloc[back[0] + 1]} after {df['t_s'].iloc[back[0]]})")  # fmt: skip
    return df[cols].reset_index(drop=True)


def replay_run(model_dir: Path, data_dir: Path, run: str, sanitize: bool = False, channel: str | None = None,
               live: bool = True, probes: pd.DataFrame | None = None, probe_params=None) -> dict:  # fmt: skip
    """Replay ``run`` of the dataset at ``data_dir`` through the exported model at ``model_dir``
    (a format 2 dataset: the error ``channel`` the model predicts, see :func:`replay_view`).

    Every control cycle (a process sample) and every reading is answered as the compensator
    answers it, with the log up to its own time (tb_replay --live): the figures are what the
    compensator achieves, cycle by cycle the values it writes. A model whose value at t is final
    only later (the screw physics between its macro steps) gives its provisional value there.
    ``live=False``: every query answered once its value is final (the values the export's parity
    check compares with the Python model). ``probes`` (:func:`read_probes`): probe readings correct
    the model as the compensator's probe input does (the C runtime's ``tb_probe``, ``probe_params``:
    :class:`thermbench.bench.adapt.ProbeParams`, default ``probe`` of ``conf/compensator.yaml``); readings
    at a probe's time are left out of the figures (they were measured, not compensated)."""
    model_dir, data_dir = Path(model_dir), Path(data_dir)
    man = read_manifest(model_dir)
    ds = load_dataset(data_dir)
    check_machine(man, model_dir, ds, data_dir)
    if ds.metadata.version == 2:
        ds = replay_view(ds, man, run, channel, data_dir)
    elif channel is not None and channel not in ds.metadata.error_channels():
        raise ExportError(f"--channel {channel!r}: {data_dir} is a format 1 dataset with one channel; leave it out")
    if run not in ds.run_ids:
        raise ExportError(f"--run {run!r}: not a run of {data_dir}; its runs: {ds.run_ids}")
    te = thermal_errors(ds)
    if "target_mm" not in te.columns:  # a format 2 log without readings
        te = te.assign(target_mm=pd.Series(dtype=float))
    te = te[te["run_id"] == run].reset_index(drop=True)
    pr = ds.process_run(run)
    q_read = pd.DataFrame({"t_s": te["t_s"].to_numpy(), "axis_mm": te["target_mm"].to_numpy()})
    q_ctrl = pd.DataFrame({"t_s": pr["t_s"].to_numpy(), "axis_mm": pr["axis_mm"].to_numpy()})
    both = pd.concat([q_read.assign(src=0), q_ctrl.assign(src=1)], ignore_index=True)
    order = np.argsort(both["t_s"].to_numpy(), kind="stable")
    # as the compensator answers (tb_replay --live): each cycle and reading with the log up to its
    # time only; before the runtime has a state nothing is written (0)
    if probes is not None:
        from ..bench.adapt import ProbeParams
        from ..config import with_defaults

        probe_params = probe_params or ProbeParams.from_config(with_defaults("compensator", {})["probe"])
        probes = probes.copy()
        if "axis_mm" not in probes:
            probes["axis_mm"] = np.interp(probes["t_s"], pr["t_s"], pr["axis_mm"])
        outside = probes[(probes["t_s"] < pr["t_s"].iloc[0]) | (probes["t_s"] > pr["t_s"].iloc[-1])]
        if len(outside):
            raise ExportError(f"--probes: a reading at t_s={outside['t_s'].iloc[0]} s is outside run {run!r} "
                              f"({pr['t_s'].iloc[0]} to {pr['t_s'].iloc[-1]} s)")  # fmt: skip
    res = replay_dir(model_dir, ds, run, both.iloc[order][["t_s", "axis_mm"]].reset_index(drop=True), sanitize=sanitize,
                     live=live, probes=probes, probe_params=probe_params if probes is not None else None)  # fmt: skip
    res.index = order
    res = res.sort_index()
    if probes is not None:  # the compensator writes the corrected value
        res["total_um"] = res["corrected_um"].where(res["rc"] == 0)
    res[["thermal_um", "total_um"]] = res[["thermal_um", "total_um"]].fillna(0.0)
    src = both["src"].to_numpy()
    rd, ctrl = res[src == 0].reset_index(drop=True), res[src == 1].reset_index(drop=True)
    readings = te[["t_s", "target_mm", "error_um", "thermal_um"]].copy()
    readings["predicted_um"] = rd["total_um"].to_numpy()
    readings["residual_um"] = readings["error_um"] - readings["predicted_um"]
    if probes is not None:
        readings["probe"] = readings["t_s"].isin(probes["t_s"]).to_numpy()
    labels = None
    if man["kind"] == "bank":
        names = [m["label"] for m in man["bank"]["members"]]
        labels = [names[i] if i >= 0 else None for i in ctrl["label"]]
        readings["condition"] = [names[i] if i >= 0 else None for i in rd["label"]]
    comp = pd.DataFrame({"t_s": ctrl["t_s"], "axis_mm": ctrl["axis_mm"], "thermal_um": ctrl["thermal_um"],
                         "compensation_um": -ctrl["total_um"]})  # fmt: skip
    if labels is not None:
        comp["condition"] = labels
    figures = {"model": man["name"], "kind": man["kind"], "run": run, "dataset": str(data_dir),
               "answers": "live (the log up to each query's time)" if live else "final",
               "frame": frame_text(ds.metadata),
               "n_readings": len(readings), "n_control_cycles": len(comp)}  # fmt: skip
    scored = readings[~readings["probe"]] if probes is not None else readings
    if probes is not None:
        figures["n_probes"] = len(probes)
        figures["probe_params"] = probe_params.as_dict()
        figures["n_readings_scored"] = len(scored)
    figures.update(compensation_figures(scored) if len(scored) else {})
    if ds.channel is not None:
        figures["channel"] = ds.channel
    if labels is not None:
        switches = int(sum(1 for a, b in zip(labels[:-1], labels[1:]) if a != b and a is not None and b is not None))
        first = next((i for i, lab in enumerate(labels) if lab is not None), None)
        figures["condition_switches"] = switches  # between conditions, after the first classification
        figures["first_condition_at_s"] = None if first is None else float(comp["t_s"].iloc[first] - comp["t_s"].iloc[0])
        figures["conditions_used"] = sorted({lab for lab in labels if lab is not None})
    cycles = cycle_curves(te, readings["predicted_um"].to_numpy()) if len(readings) else None
    return {"figures": figures, "readings": readings, "compensation": comp, "cycles": cycles}


def compensation_figures(readings: pd.DataFrame) -> dict:
    """Before/after figures over interferometer readings with ``error_um`` (as read),
    ``thermal_um`` (minus the cold reference), ``predicted_um`` and ``residual_um``
    (= error - predicted): what ``thermbench replay`` and ``thermbench sim-cnc`` report."""
    m = residual_metrics(readings["error_um"], readings["predicted_um"], readings["thermal_um"])
    return {
        "before_max_abs_um": m["max_abs_error_um"], "after_max_abs_um": m["max_abs_residual_um"],
        "before_interval_um": [float(readings["thermal_um"].min()), float(readings["thermal_um"].max())],
        "after_interval_um": [float(readings["residual_um"].min()), float(readings["residual_um"].max())],
        "before_pv_um": m["pv_error_um"], "after_pv_um": m["pv_residual_um"],
        "before_rms_um": float(np.sqrt(np.mean(readings["thermal_um"].to_numpy(dtype=float) ** 2))),
        "after_rmse_um": m["rmse_um"],
        "compensation_rate": m["compensation_rate"],
        "pv_reduction": 1.0 - m["pv_residual_um"] / m["pv_error_um"] if m["pv_error_um"] > 0 else float("nan"),
    }  # fmt: skip


def draw_errors(fig, result: dict) -> None:
    """Draw the replay's readings into ``fig`` (a matplotlib Figure): the thermal error without
    compensation and the residual with the C runtime's compensation, coloured by target."""
    f, rd = result["figures"], result["readings"]
    ax = fig.subplots(1, 2, sharey=True)
    for a, col, title in ((ax[0], "thermal_um", "without compensation"), (ax[1], "residual_um", "with compensation (C runtime)")):
        sc = a.scatter(rd["t_s"] / 3600.0, rd[col], c=rd["target_mm"], s=6, cmap="viridis")
        a.set_title(title)
        a.set_xlabel("time, h")
        a.grid(alpha=0.3)
    ax[0].set_ylabel("error at the measuring points, µm")
    fig.colorbar(sc, ax=ax, label="target, mm")
    fig.suptitle(f"{f['model']} on {f['run']}: max |error| {f['before_max_abs_um']:.1f} → {f['after_max_abs_um']:.1f} µm")


def write_replay(result: dict, out_dir: Path, force: bool = False) -> Path:
    """Write the replay's files and figures to ``out_dir``, one output of kind ``replay``
    (:func:`thermbench.outputs.output_dir`: an earlier replay there is replaced, anything
    else refused; ``force``: written beside other files, never over them).

    The figures are bare matplotlib ``Figure`` objects (no pyplot), so the caller's backend,
    e.g. a notebook's inline one, is left alone."""
    from matplotlib.figure import Figure

    f = result["figures"]
    with output_dir(out_dir, "replay", force=force) as tmp:
        (tmp / "replay.json").write_text(json.dumps(f, indent=2, allow_nan=False) + "\n", encoding="utf-8")
        result["readings"].to_csv(tmp / "readings.csv", index=False)
        result["compensation"].to_csv(tmp / "compensation.csv", index=False)
        if result["cycles"] is None:  # a log without readings: the compensation the runtime sends
            comp = result["compensation"]
            fig = Figure(figsize=(8, 4))
            ax = fig.subplots()
            ax.plot(comp["t_s"] / 3600.0, comp["compensation_um"], lw=0.8)
            ax.set_xlabel("time, h")
            ax.set_ylabel("compensation sent, µm")
            ax.set_title(f"{f['model']} on {f['run']} (no readings to compare with)")
            ax.grid(alpha=0.3)
            fig.savefig(tmp / "compensation.png", dpi=110)
            return Path(out_dir)
        fig = Figure(figsize=(11, 4))
        draw_errors(fig, result)
        fig.savefig(tmp / "errors_before_after.png", dpi=110)
        cy = result["cycles"]
        fig = Figure(figsize=(8, 4))
        ax = fig.subplots()
        ax.plot(cy["t_s"] / 3600.0, cy["before_um"], "o-", label="before (max |thermal error|)")
        ax.plot(cy["t_s"] / 3600.0, cy["after_um"], "s-", label="after (max |residual|)")
        comp = result["compensation"]
        if "condition" in comp:
            ax2 = ax.twinx()
            codes = {c: i for i, c in enumerate(sorted({c for c in comp["condition"] if isinstance(c, str)}))}
            ax2.step(comp["t_s"] / 3600.0, [codes.get(c, -1) for c in comp["condition"]], where="post", color="grey", alpha=0.5)
            ax2.set_yticks([-1, *codes.values()], ["none", *codes])
            ax2.set_ylabel("condition chosen online")
        ax.set_xlabel("time, h")
        ax.set_ylabel("per measuring cycle, µm")
        ax.grid(alpha=0.3)
        ax.legend(loc="upper left")
        fig.tight_layout()
        fig.savefig(tmp / "cycles_before_after.png", dpi=110)
    return Path(out_dir)


def format_replay(f: dict) -> str:
    if not f["n_readings"]:
        return (f"replay {f['model']} ({f['kind']}) on run {f['run']}: {f['n_control_cycles']} control cycles, "
                "no readings (a log to predict on): the compensation sent is in compensation.csv")  # fmt: skip
    lines = [
        f"replay {f['model']} ({f['kind']}) on run {f['run']}: {f['n_control_cycles']} control cycles, {f['n_readings']} readings",
        f"  before: max |error| {f['before_max_abs_um']:.2f} µm, interval [{f['before_interval_um'][0]:.2f}, {f['before_interval_um'][1]:.2f}] µm",
        f"  after:  max |error| {f['after_max_abs_um']:.2f} µm, interval [{f['after_interval_um'][0]:.2f}, {f['after_interval_um'][1]:.2f}] µm, RMS {f['after_rmse_um']:.2f} µm",
        f"  compensation rate {100 * f['compensation_rate']:.1f} %, P-V reduced by {100 * f['pv_reduction']:.1f} %",
    ]  # fmt: skip
    if str(f.get("answers", "")).startswith("live"):
        lines.insert(1, "  answered as the compensator does: each cycle and reading with the log up to its time")
    if f.get("frame"):
        lines.insert(1, f"  scored on {f['frame']}")
    if "n_probes" in f:
        lines.insert(1, f"  corrected by {f['n_probes']} probe readings (tb_probe); scored on the "
                        f"{f['n_readings_scored']} readings that were not probes")  # fmt: skip
    if "condition_switches" in f:
        if f["first_condition_at_s"] is None:
            lines.append("  classifier: no motion window was classified (no condition model used; geometric part only)")
        else:
            lines.append(f"  classifier: first condition after {f['first_condition_at_s']:.0f} s, then "
                         f"{f['condition_switches']} switches; conditions used {f['conditions_used']}")  # fmt: skip
    return "\n".join(lines)
