"""``thermbench ...``: the exit code of a command line. Parse it (:mod:`.parser`), hand it to its
command (:mod:`.commands`) or to Hydra (the train, evaluate, benchmark and export jobs), and say a user's
mistake in one line with exit 2; a programming error keeps its traceback.
"""

from __future__ import annotations

import difflib
import signal
import sys
import warnings

from .commands import (
    cmd_certs, cmd_classify, cmd_compensator, cmd_diagnose, cmd_import, cmd_iso230, cmd_linuxcnc, cmd_precompensate,
    cmd_replay, cmd_sim_cnc, cmd_simulate, cmd_station, cmd_validate,
)
from .parser import HYDRA_JOBS, build_parser


def main(argv: list[str] | None = None) -> int:
    """``thermbench ...``: the exit code. 2: a user mistake, reported in one line on stderr
    (:func:`thermbench.errors.user_errors`); any other exception is a bug and keeps its
    traceback. 141: the reader of stdout went away (``thermbench ... | head``), quietly."""
    from ..errors import BROKEN_PIPE_EXIT, GuardedStdout, StdoutClosed, stdout_closed

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
    from ..errors import report, user_errors

    argv = list(sys.argv[1:] if argv is None else argv)
    if argv and argv[0] in HYDRA_JOBS:
        from ..app import run

        return run(argv[0], argv[1:])

    parser, sub = build_parser()
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

