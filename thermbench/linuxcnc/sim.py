"""``thermbench linuxcnc sim MODEL_DIR``: the compensator in a real LinuxCNC, headless.

It writes a LinuxCNC sim configuration into ``out_dir`` and runs it once:

* ``thermbench.ini``: one X joint (trivkins, mm), ``basic_sim.tcl`` for the simulated servo
  loop, ``[AXIS_X]OFFSET_AV_RATIO`` for the external offsets, and ``[DISPLAY]DISPLAY`` =
  ``display.py``, a program on LinuxCNC's Python ``linuxcnc`` module that turns the machine
  on, homes it, runs the G-code program and exits (no GUI, no X server);
* ``thermbench.hal``: the thermal plant (:mod:`.plant`, on a scaled clock) and the
  compensator component (:mod:`.component`) loaded with ``loadusr -Wn``, their pins netted
  to the joint, the axis's external offset pins and each other, and LinuxCNC's ``sampler``
  recording, every servo period, the commanded position, the applied and requested
  offsets, the actual position (``joint.0.motor-pos-fb``), the counts written and machine
  time (``halsampler`` -> ``samples.txt``);
* ``program.ngc``: the duty cycle (a reciprocating X stroke in an ``o100 repeat`` loop,
  then a dwell while the screw cools), or the user's ``gcode``;
* ``model/``: a copy of the exported model (the LinuxCNC user must be able to read it).

LinuxCNC (``linuxcnc-uspace``) refuses to run as root: as root, ``user`` names the
unprivileged user it runs as (the directory is handed to that user). After the run
:func:`thermbench.linuxcnc.verify.check_run` checks the closed loop and the figures go to
``linuxcnc_sim.json``.
"""

from __future__ import annotations

import json
import os
import pwd
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any, Mapping

import thermbench

from ..errors import UserError
from ..outputs import output_dir
from . import verify

FILES = Path(__file__).parent / "files"


class LinuxCncSimError(UserError):
    """A set-up that cannot run (LinuxCNC missing, root without a user, a failed run)."""


def gcode(program: Mapping[str, Any]) -> str:
    """The reciprocating duty cycle: a loop of LinuxCNC's O-codes, a real interpreter feature."""
    a, b, f = float(program["start_mm"]), float(program["end_mm"]), float(program["feed_mm_min"])
    n, dwell = int(program["repeats"]), float(program["dwell_s"])
    return "\n".join([
        "( thermbench linuxcnc sim: a reciprocating X stroke, then a stop while the screw cools )",
        "G21 G90 G94 G17",
        f"G0 X{a:.3f}",
        f"o100 repeat [{n}]",
        f"  G1 X{b:.3f} F{f:.1f}",
        f"  G1 X{a:.3f}",
        "o100 endrepeat",
        f"G4 P{dwell:.3f}",
        "M2",
        "",
    ])  # fmt: skip


def ini_text(cfg: Mapping[str, Any], program_file: str) -> str:
    lo, hi = (float(v) for v in cfg["travel_mm"])
    v, a = float(cfg["max_velocity_mm_s"]), float(cfg["max_acceleration_mm_s2"])
    return f"""# written by thermbench linuxcnc sim: one X joint, simulated servo loop, external offsets, headless display
[EMC]
VERSION = 1.1
MACHINE = thermbench-linuxcnc-sim

[DISPLAY]
DISPLAY = ./display.py
OPEN_FILE = {program_file}
POSITION_OFFSET = RELATIVE
POSITION_FEEDBACK = ACTUAL

[THERMBENCH]
RESULT = display_result.json
TIMEOUT_S = {float(cfg['timeout_s'])}
SETTLE_S = {float(cfg['settle_s'])}
PLANT_RESULT = plant/closed_loop.json

[TASK]
TASK = milltask
CYCLE_TIME = 0.001

[RS274NGC]
PARAMETER_FILE = sim.var

[EMCIO]
EMCIO = io
CYCLE_TIME = 0.100

[EMCMOT]
EMCMOT = motmod
SERVO_PERIOD = 1000000

[HAL]
HALFILE = LIB:basic_sim.tcl -no_use_hal_manualtoolchange -no_sim_spindle
HALFILE = thermbench.hal

[TRAJ]
COORDINATES = X
LINEAR_UNITS = mm
ANGULAR_UNITS = degree
MAX_LINEAR_VELOCITY = {v}

[KINS]
JOINTS = 1
KINEMATICS = trivkins coordinates=X

[AXIS_X]
OFFSET_AV_RATIO = {float(cfg['offset_av_ratio'])}
MAX_VELOCITY = {v}
MAX_ACCELERATION = {a}
MIN_LIMIT = {lo}
MAX_LIMIT = {hi}

[JOINT_0]
TYPE = LINEAR
HOME_SEQUENCE = 0
MAX_VELOCITY = {v}
MAX_ACCELERATION = {a}
MIN_LIMIT = {lo}
MAX_LIMIT = {hi}
"""


def hal_text(cfg: Mapping[str, Any], sensors: list[str], python: str) -> str:
    """The HAL file: plant, compensator, nets, sampler (the snippet docs/linuxcnc.md explains)."""
    env = "env NUMBA_CACHE_DIR=numba_cache MPLBACKEND=Agg"
    plant = (f"loadusr -Wn tbplant {env} {python} linuxcnc plant benchmark={cfg['benchmark']} "
             f"time_scale={float(cfg['time_scale'])} period_s={float(cfg['period_s'])} out_dir=plant"
             + (f" probe_every_s={float(cfg['probe_every_s'])}" if cfg.get("probe_every_s") is not None else ""))  # fmt: skip
    extra = dict(_flat(cfg.get("component") or {}))
    bad = [k for k, v in extra.items() if not isinstance(v, (int, float, str, bool)) or " " in str(v)]
    if bad:
        raise LinuxCncSimError(f"config key 'component': {bad} are not plain values (a number, a word): they go on the "
                               "loadusr line of the HAL file")  # fmt: skip
    comp_over = {"time_source": "pin", "period_s": float(cfg["period_s"]), "scale_per_count": float(cfg["scale_per_count"]),
                 "log": "compensator_log.csv", **extra}  # fmt: skip
    comp = f"loadusr -Wn tbcomp {env} {python} linuxcnc component model " + " ".join(
        f"{k}={v}" for k, v in comp_over.items())
    lines = ["# written by thermbench linuxcnc sim", "# the thermal plant (scaled clock) and the compensator", plant, comp,
             "", "# the axis as both see it",
             "net tb-pos joint.0.pos-fb => tbplant.axis-pos tbcomp.axis-pos",
             "net tb-vel joint.0.vel-cmd => tbplant.axis-vel tbcomp.axis-vel",
             "net tb-time tbplant.time-s => tbcomp.time-s",
             "net sample:enable => tbcomp.machine-on tbplant.machine-on",
             "net tb-homed motion.is-all-homed => tbcomp.all-homed",
             "# the temperature pins (on a real machine: the sensors' HAL pins)"]  # fmt: skip
    lines += [f"net tb-{s} tbplant.temp.{s} => tbcomp.temp.{s}" for s in sensors]
    if cfg.get("probe_every_s") is not None:
        lines += ["# the probe (on a real machine: the touch probe cycle's result, e.g. from a probing macro)",
                  "net tb-probe tbplant.probe-um => tbcomp.probe-um",
                  "net tb-probe-valid tbplant.probe-valid => tbcomp.probe-valid"]  # fmt: skip
    lines += ["# the compensation into LinuxCNC's external offset of X",
              "net tb-counts tbcomp.eoffset-counts => axis.x.eoffset-counts",
              "net tb-scale tbcomp.eoffset-scale => axis.x.eoffset-scale",
              "net tb-enable tbcomp.eoffset-enable => axis.x.eoffset-enable",
              "net tb-clear tbcomp.eoffset-clear => axis.x.eoffset-clear",
              "net tb-eoffset axis.x.eoffset => tbplant.eoffset",
              "", "# every servo period: " + ", ".join(n for n, _, _, _ in verify.SAMPLED),
              f"loadrt sampler depth=20000 cfg={''.join(c for _, c, _, _ in verify.SAMPLED)}",
              "addf sampler.0 servo-thread"]  # fmt: skip
    lines += [f"net {sig} {pin or ''} => sampler.0.pin.{i}".replace("  ", " ")
              for i, (_, _, sig, pin) in enumerate(verify.SAMPLED)]
    lines += ["loadusr halsampler -t samples.txt", ""]
    return "\n".join(lines)


def _unprivileged(cfg: Mapping[str, Any]) -> str | None:
    """The user LinuxCNC runs as: None (this user) unless we are root."""
    if os.geteuid() != 0:
        return None
    user = cfg.get("user")
    if not user:
        raise LinuxCncSimError("config key 'user': LinuxCNC (uspace) refuses to run as root; create an unprivileged user "
                               "(useradd -m thermbench) and pass user=thermbench")  # fmt: skip
    try:
        pw = pwd.getpwnam(str(user))
    except KeyError:
        raise LinuxCncSimError(f"config key 'user': no user {user!r} on this machine (create it: useradd -m {user})") from None
    if pw.pw_uid == 0:
        raise LinuxCncSimError(f"config key 'user': {user!r} is root; LinuxCNC needs an unprivileged user")
    return str(user)


LAUNCHER = """#!{python}
# written by thermbench linuxcnc sim: runs thermbench for LinuxCNC's loadusr{how}
import site
import sys

SITE = {site!r}
if SITE:  # thermbench's environment first, ahead of the system's own packages
    before = list(sys.path)
    site.addsitedir(SITE)
    sys.path[:] = [p for p in sys.path if p not in before] + before
import runpy

sys.argv[0] = "thermbench"
runpy.run_module("thermbench", run_name="__main__", alter_sys=True)
"""


def component_python(user: str | None, display_python: str) -> tuple[str, str | None]:
    """The interpreter LinuxCNC's user starts the components with, and the site-packages to
    put first (None: the interpreter's own environment). This one when that user can run it;
    else (a root-owned interpreter, e.g. under /root, that the user cannot reach) the system
    Python of the same version with this environment's site-packages in front."""
    import sysconfig

    probe = [sys.executable, "-c", "import thermbench"]
    if user is None or subprocess.run(["runuser", "-u", user, "--", *probe], capture_output=True, cwd="/").returncode == 0:
        return sys.executable, None
    version = f"{sys.version_info[0]}.{sys.version_info[1]}"
    other = subprocess.run([display_python, "-c", "import sys; print('%d.%d' % sys.version_info[:2])"], capture_output=True, text=True)
    if other.returncode != 0 or other.stdout.strip() != version:
        raise LinuxCncSimError(f"user {user!r} cannot run {sys.executable}, and {display_python} (config key 'display_python') "
                               f"is not Python {version}: install thermbench where that user can run it")  # fmt: skip
    purelib = sysconfig.get_paths()["purelib"]
    probe = [display_python, "-c", f"import site; site.addsitedir({purelib!r}); import thermbench"]
    if subprocess.run(["runuser", "-u", user, "--", *probe], capture_output=True, cwd="/").returncode != 0:
        blocked = blocking_dirs([Path(purelib), Path(__file__).resolve().parents[2]])
        raise LinuxCncSimError(f"user {user!r} cannot reach thermbench's environment: {', '.join(map(str, blocked)) or purelib} "
                               f"not open to it (a directory on the way lacks the x permission for others): run from a "
                               f"checkout and environment that user can read")  # fmt: skip
    return display_python, purelib


def blocking_dirs(paths) -> list[Path]:
    """The directories on the way to ``paths`` that other users cannot pass (no x for others)."""
    out: list[Path] = []
    for p in paths:
        for d in [*reversed(Path(p).resolve().parents), Path(p).resolve()]:
            if d.is_dir() and not d.stat().st_mode & 0o001 and d not in out:
                out.append(d)
    return out


def write_config(stage: Path, model_dir: Path, cfg: Mapping[str, Any], sensors: list[str], launcher: str) -> None:
    """The configuration directory (see the module docstring)."""
    shutil.copytree(model_dir, stage / "model")
    if cfg.get("gcode"):
        src = Path(str(cfg["gcode"]))
        if not src.is_file():
            raise LinuxCncSimError(f"config key 'gcode': {src} is not a file")
        shutil.copyfile(src, stage / "program.ngc")
    else:
        (stage / "program.ngc").write_text(gcode(cfg["program"]))
    (stage / "thermbench.ini").write_text(ini_text(cfg, "program.ngc"))
    (stage / "thermbench.hal").write_text(hal_text(cfg, sensors, "./tb_launch"))
    (stage / "tb_launch").write_text(launcher)
    (stage / "tb_launch").chmod(0o755)
    display = (FILES / "headless_display").read_text().replace("#!/usr/bin/python3", f"#!{cfg['display_python']}", 1)
    (stage / "display.py").write_text(display)
    (stage / "display.py").chmod(0o755)
    (stage / "numba_cache").mkdir()


def run_linuxcnc(stage: Path, user: str | None, timeout_s: float) -> subprocess.CompletedProcess:
    """``linuxcnc thermbench.ini`` in ``stage`` (as ``user`` when given), under ``script`` so that
    LinuxCNC prints to our pipe (without a terminal it writes to temporary files it deletes). It
    runs in a session of its own: past ``timeout_s`` the whole of it (realtime, task, components)
    is killed, and that is a :class:`LinuxCncSimError`."""
    import signal

    cmd = ["env", f"HOME={stage}", "script", "-qec", "linuxcnc thermbench.ini", "/dev/null"]
    if user is not None:
        cmd = ["runuser", "-u", user, "--", *cmd]
    proc = subprocess.Popen(cmd, cwd=stage, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            stdin=subprocess.DEVNULL, start_new_session=True)  # fmt: skip
    try:
        out, err = proc.communicate(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.communicate()
        subprocess.run(["pkill", "-KILL", "-s", str(proc.pid)], check=False)
        raise LinuxCncSimError(f"LinuxCNC did not finish within {timeout_s:g} s (config key 'timeout_s' + 120 s); "
                               "it was stopped") from None  # fmt: skip
    return subprocess.CompletedProcess(cmd, proc.returncode, out, err)


def component_overrides(extra: Mapping[str, Any]) -> dict[str, Any]:
    """Key ``component`` (overrides of conf/linuxcnc_component.yaml, nested or dotted: ``{probe:
    {r_um2: 0.25}}``, ``+component.probe.r_um2=0.25``) as a nested mapping (the HAL file's loadusr
    line gets its leaves as ``key=value``); a key the component does not have is an error naming it."""
    from ..config import ConfigError, with_defaults

    if not isinstance(extra, Mapping):
        raise LinuxCncSimError(f"config key 'component': expected a mapping of conf/linuxcnc_component.yaml's keys, got {extra!r}")
    nested: dict[str, Any] = {}
    for k, v in extra.items():
        cur = nested
        *head, last = str(k).split(".")
        for h in head:
            cur = cur.setdefault(h, {})
        if isinstance(v, Mapping):
            cur.setdefault(last, {}).update(dict(v))
        else:
            cur[last] = v
    try:
        with_defaults("linuxcnc_component", nested)
    except ConfigError as exc:
        raise LinuxCncSimError(f"config key 'component': {str(exc).split(': ', 1)[-1]} "
                               "(the keys are conf/linuxcnc_component.yaml's)") from None

    return nested


def _flat(d: Mapping[str, Any], prefix: str = ""):
    """A nested mapping's leaves as (dotted key, value) pairs."""
    for k, v in d.items():
        if isinstance(v, Mapping):
            yield from _flat(v, f"{prefix}{k}.")
        else:
            yield f"{prefix}{k}", v


def run_sim(model_dir: str | Path, cfg: Mapping[str, Any] | None = None, say=None) -> dict:
    """Write the configuration, run LinuxCNC once, check the run; returns the figures (also in
    ``out_dir/linuxcnc_sim.json``). A run that fails is a :class:`LinuxCncSimError` naming why;
    its directory is kept for a look."""
    from ..config import with_defaults
    from ..export.native import LiveModel

    cfg = dict(cfg or {})
    extra = cfg.pop("component", None) or {}  # the component's own keys: checked against its config
    cfg = with_defaults("linuxcnc_sim", cfg)
    cfg["component"] = component_overrides(extra)
    say = say or (lambda line: None)
    every = cfg.get("probe_every_s")
    if every is not None and (isinstance(every, bool) or not isinstance(every, (int, float)) or not every > 0):
        raise LinuxCncSimError(f"config key 'probe_every_s': expected null or a number of machine seconds > 0, got {every!r}")
    if shutil.which("linuxcnc") is None:
        raise LinuxCncSimError("LinuxCNC is not installed (Debian: apt-get install --no-install-recommends linuxcnc-uspace)")
    user = _unprivileged(cfg)
    python, site_dir = component_python(user, str(cfg["display_python"]))
    how = "" if site_dir is None else f" (user {user} cannot run {sys.executable}: {python} with its site-packages)"
    launcher = LAUNCHER.format(python=python, site=site_dir, how=how)
    model_dir = Path(model_dir)
    sensors = list(LiveModel(model_dir).temperatures)  # a model directory the runtime refuses fails here, in one line
    out = Path(str(cfg["out_dir"]))
    failure = None
    with output_dir(out, "linuxcnc-sim", force=bool(cfg["force"]), force_option="force=true") as stage:
        write_config(stage, model_dir, cfg, sensors, launcher)
        stage.chmod(0o755)
        if user is not None:
            for p in [stage, *stage.rglob("*")]:
                shutil.chown(p, user)
        say(f"linuxcnc sim: running {stage / 'thermbench.ini'}" + (f" as {user}" if user else ""))
        proc = run_linuxcnc(stage, user, float(cfg["timeout_s"]) + 120.0)
        (stage / "linuxcnc_output.txt").write_text(proc.stdout + proc.stderr)
        shutil.rmtree(stage / "numba_cache", ignore_errors=True)
        result_file = stage / "display_result.json"
        result = json.loads(result_file.read_text()) if result_file.exists() else {"ok": False, "failure": "no result"}
        if not result.get("ok"):
            failure = f"the LinuxCNC run failed: {result.get('failure')}; LinuxCNC said: {_tail(proc.stdout + proc.stderr)}"
            figures = {"ok": False, "failure": failure, "display": result}
        else:
            try:
                figures = verify.check_run(stage, cfg)
            except Exception as exc:  # a run whose records cannot be checked: kept for a look
                failure = f"checking the run failed: {type(exc).__name__}: {exc}"
                figures = {"ok": False, "failure": failure}
            figures["display"] = result
        (stage / "linuxcnc_sim.json").write_text(json.dumps(figures, indent=2, default=float) + "\n")
    if failure:
        raise LinuxCncSimError(f"{failure} (see {out})".replace(str(stage), str(out)))
    return figures


def _tail(text: str, n: int = 6) -> str:
    lines = [ln for ln in text.splitlines() if ln.strip() and not ln.startswith("task: main loop took")]
    return " | ".join(lines[-n:])


__getattr__ = thermbench.moved_names(__name__)  # SAMPLED: in .verify, the records the checks read
