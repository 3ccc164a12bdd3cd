"""Build and drive the portable C runtime (``embedded/``) from Python.

:func:`build` compiles the runtime with one of its host tools by gcc (C99, ``-Wall
-Wextra -Werror``), cached by a hash of the sources and flags, :func:`build_shared` the runtime
alone as a shared library (the in-process binding, :mod:`.native`); :func:`replay`
streams a run's process log through it (``tb_replay``) and returns its
predictions at query points; :func:`info` reads each file's kind, size and state
bytes as the runtime sees them.
"""

from __future__ import annotations

import hashlib
import io
import os
import shutil
import subprocess
import tempfile
from pathlib import Path
from typing import Sequence

import numpy as np
import pandas as pd

from .._resources import project_dir

CFLAGS = ("-std=c99", "-Wall", "-Wextra", "-Werror", "-pedantic", "-O2")
SANITIZE = ("-fsanitize=address,undefined,float-cast-overflow", "-fno-omit-frame-pointer", "-fno-sanitize-recover=all",
            "-g")  # fmt: skip


class RuntimeUnavailable(RuntimeError):
    """The C runtime cannot be built or run here (no compiler, sources missing, ...)."""


class RuntimeFailed(RuntimeError):
    """The C runtime ran and reported an error (its message is included)."""


def embedded_dir() -> Path:
    """``$THERMBENCH_EMBEDDED_DIR``, else the ``embedded/`` the package carries (a wheel), else the one
    at the top of a source checkout (thermbench/_resources.py)."""
    d, tried = project_dir("embedded", "THERMBENCH_EMBEDDED_DIR", "src/tb_runtime.c")
    if not (d / "src" / "tb_runtime.c").exists():
        where = " nor ".join(str(t) for t in tried)
        raise RuntimeUnavailable(f"the C runtime sources are not at {where}; set THERMBENCH_EMBEDDED_DIR to the project's embedded/")
    return d


def cache_dir() -> Path:
    base = os.environ.get("THERMBENCH_CACHE_DIR") or os.path.join(os.path.expanduser("~"), ".cache", "thermbench")
    return Path(base) / "embedded"


def runtime_sources() -> list[Path]:
    """The runtime's C files: the core ``src/tb_runtime.c``, a file per model kind and per physics
    effect (``src/tb_registry.def`` lists them): every ``src/*.c``."""
    return sorted((embedded_dir() / "src").glob("*.c"))


def sources(tool: str) -> list[Path]:
    return [*runtime_sources(), embedded_dir() / "tools" / f"{tool}.c"]


def build(tool: str = "tb_replay", extra_flags: Sequence[str] = (), sanitize: bool = False, cc: str | None = None) -> Path:
    """Compile ``embedded/tools/<tool>.c`` with the runtime; returns the executable (cached)."""
    return _compile(tool, sources(tool), extra_flags, sanitize, cc)


def build_shared(sanitize: bool = False, cc: str | None = None) -> Path:
    """Compile the runtime alone (``src/*.c``) as a shared library for in-process use
    (:mod:`.native`); returns ``libtb_runtime-<hash>.so`` (cached like :func:`build`). A
    ``sanitize`` build loads only into a process with the sanitizer runtimes preloaded."""
    return _compile("libtb_runtime", runtime_sources(), ("-shared", "-fPIC"), sanitize, cc, suffix=".so")


def _compile(stem: str, srcs: Sequence[Path], extra_flags: Sequence[str], sanitize: bool, cc: str | None,
             suffix: str = "") -> Path:  # fmt: skip
    """gcc ``srcs`` with :data:`CFLAGS` into ``<cache_dir>/<stem>-<hash><suffix>``, the hash over the
    sources, the headers (public and internal, ``src/*.def``), the compiler and the flags; written
    atomically, reused when present."""
    cc = cc or os.environ.get("CC", "gcc")
    if shutil.which(cc) is None:
        raise RuntimeUnavailable(f"no C compiler {cc!r} on PATH: the C runtime needs one (install gcc)")
    d = embedded_dir()
    flags = [*CFLAGS, *(SANITIZE if sanitize else ()), *extra_flags, f"-I{d / 'include'}"]
    h = hashlib.sha256()
    headers = sorted([*(d / "src").glob("*.h"), *(d / "src").glob("*.def"), *(d / "include").glob("*.h"),
                      *(d / "tools").glob("*.h")])  # fmt: skip
    for p in [*srcs, *headers]:
        h.update(p.name.encode())
        h.update(p.read_bytes())
    h.update(" ".join([cc, *flags]).encode())
    out = cache_dir() / f"{stem}-{h.hexdigest()[:16]}{suffix}"
    if out.exists():
        return out
    out.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{out.name}.", dir=out.parent)
    os.close(fd)
    try:
        cmd = [cc, *flags, *map(str, srcs), "-o", tmp, "-lm"]
        res = subprocess.run(cmd, capture_output=True, text=True)
        if res.returncode != 0:
            raise RuntimeFailed(f"compiling the C runtime failed ({' '.join(cmd)}):\n{res.stderr}")
        os.replace(tmp, out)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return out


def stream_text(samples: pd.DataFrame, temps: Sequence[str], queries: pd.DataFrame, probes: pd.DataFrame | None = None) -> str:
    """The ``tb_replay`` input: queries (``t_s``, ``axis_mm``) then samples (``t_s``, ``axis_mm``,
    ``feed_mm_min``, optional ``load_N`` and ``measuring``, and the ``temps`` columns). ``probes``
    (``t_s``, ``axis_mm``, ``measured_um``): probe readings, merged with the queries in time order
    (a query at a probe's time before it: the correction it gets is the one before the probe)."""
    n = len(samples)
    cols = [samples["t_s"], samples["axis_mm"], samples["feed_mm_min"],
            samples["load_N"] if "load_N" in samples else np.zeros(n),
            samples["measuring"].astype(int) if "measuring" in samples else np.zeros(n, dtype=int)]  # fmt: skip
    arr = np.column_stack([np.asarray(c, dtype=float) for c in cols] + [samples[c].to_numpy(dtype=float) for c in temps])
    recs = [(t, 0, f"Q {t!r} {x!r}") for t, x in zip(queries["t_s"].astype(float), queries["axis_mm"].astype(float))]
    if probes is not None and len(probes):
        recs += [(t, 1, f"P {t!r} {x!r} {m!r}") for t, x, m in zip(probes["t_s"].astype(float), probes["axis_mm"].astype(float),
                                                                   probes["measured_um"].astype(float))]  # fmt: skip
        recs.sort(key=lambda r: (r[0], r[1]))
    lines = [r[2] for r in recs]
    fmt = "S " + " ".join(["%.17g"] * 4 + ["%d"] + ["%.17g"] * len(temps))
    lines += [fmt % (r[0], r[1], r[2], r[3], int(r[4]), *r[5:]) for r in arr]
    return "\n".join(lines) + "\n"


def run_tool(exe: Path, args: Sequence[str], stdin: str = "", env: dict | None = None, valgrind: Sequence[str] = ()) -> str:
    cmd = [*valgrind, str(exe), *map(str, args)]
    res = subprocess.run(cmd, input=stdin, capture_output=True, text=True, env=env)
    if res.returncode != 0:
        raise RuntimeFailed(f"the C runtime ({exe.name}) stopped: {res.stderr.strip()[-2000:]}")
    return res.stdout


#: tb_runtime.h: the runtime has no state yet (before its first samples are through)
TB_E_NOTREADY = -14


def replay(files: Sequence[Path], samples: pd.DataFrame, temps: Sequence[str], queries: pd.DataFrame,
           bank: bool = False, sanitize: bool = False, exe: Path | None = None, lenient: bool = False,
           live: bool = False, probes: pd.DataFrame | None = None, probe_params=None,
           guard: Path | None = None, faults: Path | None = None) -> pd.DataFrame:  # fmt: skip
    """Run the C runtime over ``samples`` and answer ``queries``: a DataFrame with ``t_s``,
    ``axis_mm``, ``thermal_um``, ``total_um``, ``label`` (bank condition index, -1 none), ``rc``.
    ``lenient``: samples the runtime refuses are skipped (as a compensator would), not an error.
    ``live``: each query answered with the samples up to its time only, as the compensator
    answers for the time it writes (tb_replay --live); a query before the runtime has a state
    keeps its code ``TB_E_NOTREADY`` and NaN values (the compensator holds there). ``probe_params``
    (:class:`thermbench.bench.adapt.ProbeParams`): the probe readings ``probes`` correct the model by
    ``tb_probe``, and each answer gets ``corrected_um`` and ``var_um2``. ``guard``: an envelope
    file (:mod:`.guard`; needs ``live``): each answer gets ``distance``, the extrapolation
    guard's at the last sample before it (``tb_guard``; 0 inside the envelope). ``faults``: a faults
    file (:mod:`.faultfile`; needs ``live``): the model reads each sample's temperatures as
    ``tb_faults_step`` gives them, and each answer gets :data:`FAULT_COLUMNS`: the total (or the
    probe-corrected total) bounded by ``tb_faults_bound`` (one series per ``axis_mm``), whether a
    bound acted, and each sensor's rule so far (a digit per sensor, ``TB_FAULT_*``: 0 healthy)."""
    exe = exe or build("tb_replay", sanitize=sanitize)
    return replay_text(exe, files, stream_text(samples, temps, queries, probes if probe_params is not None else None),
                       bank=bank, lenient=lenient, live=live, probe_params=probe_params, guard=guard, faults=faults)  # fmt: skip


#: tb_replay's answer to a query, one line each
REPLAY_COLUMNS = {"t_s": float, "axis_mm": float, "thermal_um": float, "total_um": float, "label": int, "rc": int}
#: what an answer adds with a faults file (tb_replay --faults)
FAULT_COLUMNS = {"bounded_um": float, "bounded": int, "rules": str}
#: the rule of each digit of ``rules`` (TB_FAULT_* of tb_runtime.h; 0: healthy)
FAULT_RULES = (None, "open", "range", "rate", "stuck", "others")


def probe_args(params) -> list[str]:
    """``tb_replay --probe QB QG R B0 G0`` for :class:`thermbench.bench.adapt.ProbeParams` ``params``."""
    return ["--probe", *(repr(float(v)) for v in (params.q_bias_um2_per_h, params.q_gain_per_h, params.r_um2,
                                                   params.bias0_um, params.gain0))]  # fmt: skip


def replay_text(exe: Path, files: Sequence[Path], text: str, bank: bool = False, lenient: bool = False,
                live: bool = False, probe_params=None, guard: Path | None = None,
                faults: Path | None = None) -> pd.DataFrame:  # fmt: skip
    """:func:`replay` of an input already written by :func:`stream_text` (one text for several builds)."""
    if (guard is not None or faults is not None) and not live:
        raise ValueError("replay: a guard or a faults file answers live (live=True)")
    args = ((["--lenient"] if lenient else []) + (["--live"] if live else []) + (probe_args(probe_params) if probe_params else [])
            + (["--guard", str(guard)] if guard is not None else []) + (["--faults", str(faults)] if faults is not None else [])
            + (["--bank"] if bank else []) + [str(f) for f in files])  # fmt: skip
    out = run_tool(exe, args, text)
    cols = {**REPLAY_COLUMNS, **({"corrected_um": float, "var_um2": float} if probe_params else {}),
            **({"distance": float} if guard is not None else {}), **(FAULT_COLUMNS if faults is not None else {})}  # fmt: skip
    if not out.strip():
        df = pd.DataFrame({c: pd.Series(dtype=t) for c, t in cols.items()})
    else:  # single spaces, %.17g (nan before a state): pandas' C parser
        df = pd.read_csv(io.StringIO(out), sep=" ", header=None, names=list(cols), dtype=cols)
    if live:
        df.loc[df["rc"] == TB_E_NOTREADY, ["thermal_um", "total_um"]] = np.nan
    bad = df[(df["rc"] != 0) & ~((df["rc"] == TB_E_NOTREADY) & live)]
    if not bad.empty:
        raise RuntimeFailed(f"the runtime could not answer {len(bad)} of {len(df)} queries (first: t={bad['t_s'].iloc[0]} s, "
                            f"code {bad['rc'].iloc[0]})")  # fmt: skip
    return df


def info(files: Sequence[Path], extra_flags: Sequence[str] = ()) -> pd.DataFrame:
    """Per file, as the runtime (built with ``extra_flags``, e.g. ``-DTB_SINGLE``) sees it: ``kind``,
    ``file_bytes``, ``state_bytes`` (the arena its running state needs) and ``model_bytes`` (the
    ``tb_model`` handle)."""
    out = run_tool(build("tb_replay", extra_flags), ["--info", *map(str, files)])
    rows = [ln.split() for ln in out.splitlines() if ln.strip()]
    df = pd.DataFrame(rows, columns=["file", "kind", "file_bytes", "state_bytes", "model_bytes"])
    return df.astype({"kind": int, "file_bytes": int, "state_bytes": int, "model_bytes": int})
