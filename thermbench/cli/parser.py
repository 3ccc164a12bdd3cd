"""The ``thermbench`` command line's parser: its commands, their options and how a mistake in them is
said (one line, exit 2). The commands themselves are in :mod:`.commands`.
"""

from __future__ import annotations

import argparse
import math

from .. import __version__

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


def build_parser() -> tuple[_Parser, argparse._SubParsersAction]:
    """The ``thermbench`` parser and its sub-parsers, one per command (the Hydra jobs are not among them:
    :func:`thermbench.cli.main` hands those to Hydra before parsing)."""
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
    return parser, sub
