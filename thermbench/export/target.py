"""The C runtime on its target: a Cortex-M4F (seed 002's STM32F407) emulated by QEMU.

:func:`build` cross-compiles the runtime (``embedded/src``), the start-up code and the
firmware-style harness (``embedded/target``) with ``arm-none-eabi-gcc`` for the Cortex-M4F
(``-mcpu=cortex-m4 -mthumb -mfloat-abi=hard -mfpu=fpv4-sp-d16``) in double or single precision
(``TB_REAL``), links the model files (and an envelope file for the extrapolation guard) into flash
(``.incbin``) and returns the firmware image; :func:`replay` runs it on QEMU's ``mps2-an386`` board
with semihosting over a run's process log and returns the predictions, as
:func:`thermbench.export.runtime.replay` does on the host (live, with probe readings corrected by
``tb_probe``, with ``tb_guard``'s distance), and what the run measured.

Needs Debian's ``gcc-arm-none-eabi``, ``libnewlib-arm-none-eabi`` and ``qemu-system-arm``
(``make target-test`` installs them: tools/sysdeps.sh); without them :class:`~.runtime.RuntimeUnavailable` says so.
"""

from __future__ import annotations

import hashlib
import os
import re
import shutil
import subprocess
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import pandas as pd

from . import runtime
from .runtime import RuntimeFailed, RuntimeUnavailable, cache_dir, embedded_dir, runtime_sources, stream_text
from .fileformat import Kind

CC = "arm-none-eabi-gcc"
QEMU = "qemu-system-arm"
PACKAGES = "gcc-arm-none-eabi libnewlib-arm-none-eabi qemu-system-arm"
CPU_FLAGS = ("-mcpu=cortex-m4", "-mthumb", "-mfloat-abi=hard", "-mfpu=fpv4-sp-d16")
CFLAGS = ("-std=c99", "-Wall", "-Wextra", "-Werror", "-O2", "-ffunction-sections", "-fdata-sections")
PRECISIONS = {"double": (), "float": ("-DTB_SINGLE", "-Wdouble-promotion", "-ffp-contract=fast")}  # single: no double arithmetic (tb_runtime.h)


def toolchain() -> tuple[str, str]:
    """The cross compiler and the emulator, or :class:`RuntimeUnavailable` naming the packages."""
    missing = [t for t in (CC, QEMU) if shutil.which(t) is None]
    if missing:
        raise RuntimeUnavailable(f"{' and '.join(missing)} not on PATH: the target build needs "
                                 f"'apt-get install {PACKAGES}'")  # fmt: skip
    return CC, QEMU


@dataclass
class Firmware:
    """A linked image: its ELF and the flash and RAM it takes (``arm-none-eabi-size``)."""

    elf: Path
    text_bytes: int
    data_bytes: int
    bss_bytes: int
    icount_shift: int = 0  # QEMU's -icount shift the harness counts instructions for (build)

    @property
    def flash_bytes(self) -> int:
        return self.text_bytes + self.data_bytes


def _target_dir() -> Path:
    return embedded_dir() / "target"


def _hash(paths: Sequence[Path], *extra: str) -> str:
    h = hashlib.sha256()
    for p in paths:
        h.update(p.name.encode())
        h.update(p.read_bytes())
    for e in extra:
        h.update(e.encode())
    return h.hexdigest()[:16]


def _run(cmd: Sequence[str], what: str, cwd: Path | None = None) -> str:
    res = subprocess.run(list(map(str, cmd)), capture_output=True, text=True, cwd=cwd)
    if res.returncode != 0:
        raise RuntimeFailed(f"{what} failed ({' '.join(map(str, cmd))}):\n{res.stderr.strip()[-3000:]}")
    return res.stdout


def build(files: Sequence[Path], precision: str = "double", arena_bytes: int = 16384, offset: int = 0,
          trap_unaligned: bool = False, guard: Path | None = None, icount_shift: int = 0,
          faults: Path | None = None) -> Firmware:  # fmt: skip
    """The firmware image running ``files`` (one model, or a bank: the classifier then the
    members in class order) from flash, in ``precision`` ("double" or "float"), with a static
    arena of ``arena_bytes``. ``offset``: the first file starts this many bytes past an
    8-byte boundary (the alignment tests); ``trap_unaligned``: unaligned accesses fault;
    ``guard``: an envelope file (the export's ``envelope.tbm``) linked into flash beside the models,
    followed by ``tb_guard`` over the samples; ``faults``: a faults file (the export's ``faults.tbm``)
    linked beside them, the sensor checks and bounds of ``tb_faults``; ``icount_shift`` (0 to 3): the image counts
    instructions for ``qemu -icount shift=icount_shift``, in steps of 40 >> shift (:func:`run` runs
    it so). Cached by a hash of the sources, the files and the options."""
    if precision not in PRECISIONS:
        raise ValueError(f"precision: expected one of {sorted(PRECISIONS)}, got {precision!r}")
    if icount_shift not in range(4):
        raise ValueError(f"icount_shift: expected 0 to 3 (40 >> shift instructions per SysTick tick), got {icount_shift!r}")
    cc, _ = toolchain()
    d, t = embedded_dir(), _target_dir()
    files = [Path(f) for f in files]
    guard = Path(guard) if guard is not None else None
    faults = Path(faults) if faults is not None else None
    harness = [*PRECISIONS[precision], f"-DTB_ARENA_BYTES={int(arena_bytes)}", *(["-DTB_TRAP_UNALIGNED"] if trap_unaligned else []),
               *([f"-DTB_ICOUNT_SHIFT={icount_shift}"] if icount_shift else [])]  # fmt: skip
    objs = _objects(precision)  # the runtime and the start-up: one compilation per precision
    key = _hash([t / "tb_target_main.c", d / "tools" / "tb_stream.h", t / "stm32f407.ld", *objs, *files], cc, *harness,
                f"offset={offset}", *([f"guard={_hash([guard])}"] if guard is not None else []),
                *([f"faults={_hash([faults])}"] if faults is not None else []))  # fmt: skip
    own = lambda work: [_compile(cc, s, work, harness) for s in (t / "tb_target_main.c", work / "models.S")]  # noqa: E731
    specs = ["--specs=rdimon.specs", "-u", "_printf_float", "-u", "_scanf_float"]  # semihosting stdio
    fw = _sized(_linked(key, files, offset, objs, own, specs, "linking the firmware", guard, faults))
    fw.icount_shift = icount_shift
    return fw


def _linked(key: str, files: Sequence[Path], offset: int, objs: Sequence[Path], own, specs: Sequence[str], what: str,
            guard: Path | None = None, faults: Path | None = None) -> Path:  # fmt: skip
    """``<cache>/target/<key>/firmware.elf``: ``objs`` and the objects ``own(work)`` compiles (after
    ``models.S`` holds ``files``, the envelope file ``guard`` and the faults file ``faults``, in flash) linked by the STM32F407
    script with newlib-nano and ``specs``; made in a temporary directory and renamed (reused when present)."""
    cc, _ = toolchain()
    out_dir = cache_dir() / "target" / key
    elf = out_dir / "firmware.elf"
    if not elf.exists():
        out_dir.parent.mkdir(parents=True, exist_ok=True)
        work = Path(tempfile.mkdtemp(prefix=f".{key}.", dir=out_dir.parent))
        try:
            (work / "models.S").write_text(_models_asm(files, offset, guard, faults))
            _run([cc, *CPU_FLAGS, "-nostartfiles", "--specs=nano.specs", *specs, f"-T{_target_dir() / 'stm32f407.ld'}",
                  "-Wl,--gc-sections", f"-Wl,-Map={work / 'firmware.map'}", *objs, *own(work), "-lm", "-o",
                  work / "firmware.elf"], what, cwd=work)  # fmt: skip
            os.replace(work, out_dir)
        finally:
            if work.exists():
                shutil.rmtree(work)
    return elf


def _qemu(elf: Path, cwd: str | None = None, timeout_s: float = 600.0, icount: bool = False,
          shift: int = 0) -> subprocess.CompletedProcess:  # fmt: skip
    """``elf`` on QEMU's mps2-an386 with semihosting (``icount``: one instruction per 2^``shift`` virtual ns)."""
    _, qemu = toolchain()
    cmd = [qemu, "-M", "mps2-an386", "-nographic", "-monitor", "none", "-serial", "none",
           *(["-icount", f"shift={int(shift)}"] if icount else []), "-semihosting-config", "enable=on,target=native",
           "-kernel", str(elf)]  # fmt: skip
    return subprocess.run(cmd, capture_output=True, text=True, cwd=cwd, timeout=timeout_s)


def _compile(cc: str, src: Path, work: Path, defs: Sequence[str]) -> Path:
    d = embedded_dir()
    o = work / (src.stem + ".o")
    _run([cc, *CPU_FLAGS, *CFLAGS, *defs, "-fstack-usage", f"-I{d / 'include'}", f"-I{d / 'src'}", "-c", src, "-o", o],
         f"compiling {src.name} for the Cortex-M4F", cwd=work)  # fmt: skip
    return o


def _objects(precision: str) -> list[Path]:
    """The runtime's and the start-up's objects (with their ``.su`` stack-usage files) for
    ``precision``, compiled once and cached by a hash of the sources, headers and flags."""
    cc, _ = toolchain()
    d, t = embedded_dir(), _target_dir()
    srcs = [*runtime_sources(), t / "startup_m4.c", t / "tb_target_semihost.c"]
    headers = sorted([*(d / "src").glob("*.h"), *(d / "src").glob("*.def"), *(d / "include").glob("*.h")])
    key = _hash([*srcs, *headers], cc, *CPU_FLAGS, *CFLAGS, *PRECISIONS[precision])
    out_dir = cache_dir() / "target" / f"obj-{precision}-{key}"
    if not out_dir.exists():
        out_dir.parent.mkdir(parents=True, exist_ok=True)
        work = Path(tempfile.mkdtemp(prefix=f".obj.{key}.", dir=out_dir.parent))
        try:
            for s in srcs:
                _compile(cc, s, work, PRECISIONS[precision])
            os.replace(work, out_dir)
        except OSError:
            if not out_dir.exists():  # another process made it first: theirs serves
                raise
        finally:
            if work.exists():
                shutil.rmtree(work)
    return sorted(out_dir.glob("*.o"))


#: TB_KIND_* (tb_runtime.h) -> the kind's name in tb_registry.def: fileformat.Kind's, lower case
#: (tests/test_runtime_contract.py checks the header and the registry against it)
KIND_CODES = {int(k): k.name.lower() for k in Kind}


def image(file: Path, precision: str = "float", arena_bytes: int = 16384) -> Firmware:
    """The smallest firmware running one model ``file`` from flash (``embedded/target/tb_target_min.c``):
    the runtime with only the file's kind in its table (``TB_REGISTRY``: the linker leaves the
    other kinds out; a physics model keeps every effect), the start-up and no stdio. Its
    ``flash_bytes`` is what a compensator's image needs at least for this model; it is run on
    QEMU, which must exit 0 (the model opened and started)."""
    cc, _ = toolchain()
    d, t = embedded_dir(), _target_dir()
    file = Path(file)
    head = file.read_bytes()[:48]
    code = int.from_bytes(head[6:8], "little")
    kind = KIND_CODES.get(code)
    if kind is None:
        raise ValueError(f"{file}: not a model file of a known kind")
    kinds = {kind}
    if code == int(Kind.ENSEMBLE):  # and its members' kinds: dims[1] is their set (tb_kind_ensemble.c)
        mask = int.from_bytes(head[16:20], "little")
        kinds |= {KIND_CODES[k] for k in KIND_CODES if mask >> k & 1}
    reg = [ln for ln in (d / "src" / "tb_registry.def").read_text().splitlines()
           if ln.startswith("TB_EFFECT(") or ln.startswith("TB_KIND(") and ln.rstrip(")").split(", ")[-1] in kinds]  # fmt: skip
    defs = [*PRECISIONS[precision], f"-DTB_ARENA_BYTES={int(arena_bytes)}"]
    objs = [o for o in _objects(precision) if o.stem not in ("tb_registry",)]
    key = _hash([t / "tb_target_min.c", d / "src" / "tb_registry.c", t / "stm32f407.ld", *objs, file], cc, *defs, *reg)

    def own(work: Path) -> list[Path]:
        (work / "one_kind.def").write_text("\n".join(reg) + "\n")
        return [_compile(cc, t / "tb_target_min.c", work, defs), _compile(cc, work / "models.S", work, defs),
                _compile(cc, d / "src" / "tb_registry.c", work, [*defs, f'-DTB_REGISTRY="{work / "one_kind.def"}"'])]  # fmt: skip

    elf = _linked(f"min-{key}", [file], 0, objs, own, ["--specs=nosys.specs"], "linking the minimal firmware")
    res = _qemu(elf, timeout_s=120.0)
    if res.returncode != 0:
        raise RuntimeFailed(f"the minimal firmware for {file} stopped (QEMU exit {res.returncode}): "
                            f"{(res.stdout + res.stderr).strip()[-1000:]}")  # fmt: skip
    return _sized(elf)


def stack_frames(precision: str = "double") -> dict[str, int]:
    """Each runtime function's own stack frame on the target, bytes, as gcc ``-fstack-usage``
    reports it (``file.c:function``; the deepest call chain is what :func:`replay` measures)."""
    out = {}
    for su in sorted(_objects(precision)[0].parent.glob("*.su")):
        for ln in su.read_text().splitlines():
            where, size, _ = ln.rsplit("\t", 2)
            out[f"{Path(where.split(':')[0]).name}:{where.rsplit(':', 1)[1]}"] = int(size)
    return out


#: libgcc's software double-precision and 64-bit routines (the Cortex-M4F's FPU is single only) and
#: newlib's double-precision <math.h>: none may be reachable from the runtime in single precision
SOFT_ROUTINE = re.compile(r"^(__aeabi_(d\w+|[a-z]*2d|f2d|[lu]*l2f|f2u?lz|u?ldivmod|lmul)|__(add|sub|mul|div)df3|"
                          r"__(eq|ne|lt|le|gt|ge|un|cmp)df2|__extendsfdf2|__truncdfsf2|__fix\w*df\w*|__float\w*df|__u?(divmod|div|mod)di[34]|"
                          r"__ieee754_(?!\w*f$)\w+|(exp|expm1|log|log1p|pow|sqrt|sin|cos|tan|tanh|sinh|cosh|erf|erfc|"
                          r"floor|ceil|fabs|fmod|round|trunc|ldexp|frexp|scalbn|modf|copysign)(_r)?)$")


def reached_routines(fw: Firmware) -> dict[str, list[str]]:
    """Every function outside the runtime that the runtime's code can reach in ``fw`` (direct calls
    and tail branches, followed through the libraries; the runtime's own indirect calls go to
    runtime functions, all of which are roots): routine name -> the runtime functions that reach
    it. From the image's disassembly and its link map (which input object each function came from)."""
    own = {}  # address -> name of a function compiled from embedded/src
    for m in re.finditer(r"^ \.text\.(\S+)\s+0x([0-9a-f]+)\s+0x[0-9a-f]+ (\S+)$",
                         (fw.elf.parent / "firmware.map").read_text(), re.M):  # fmt: skip
        if Path(m.group(3)).stem in {Path(s).stem for s in runtime_sources()}:
            own[int(m.group(2), 16)] = m.group(1)
    dis = _run(["arm-none-eabi-objdump", "-d", "--no-show-raw-insn", fw.elf], "arm-none-eabi-objdump")
    names, calls, cur = {}, {}, None
    for ln in dis.splitlines():
        head = re.match(r"^([0-9a-f]+) <([^>]+)>:$", ln)
        if head:
            cur = int(head.group(1), 16)
            names[cur] = head.group(2)
            calls[cur] = set()
            continue
        br = re.search(r"\s(?:bl|b|b\.n|b\.w|blx)(?:\.w)?\s+([0-9a-f]+) <([^>+]+)>$", ln)
        if br and cur is not None and int(br.group(1), 16) != cur:
            calls[cur].add(int(br.group(1), 16))
    out: dict[str, list[str]] = {}
    for root in own:
        seen, todo = {root}, [root]
        while todo:
            for nxt in calls.get(todo.pop(), ()):
                if nxt not in seen and nxt not in own:
                    seen.add(nxt)
                    todo.append(nxt)
        for a in seen - {root}:
            out.setdefault(names.get(a, hex(a)), []).append(own[root])
    return {k: sorted(set(v)) for k, v in sorted(out.items())}


def soft_routines(fw: Firmware) -> dict[str, list[str]]:
    """The software double-precision and 64-bit routines (:data:`SOFT_ROUTINE`) the runtime in ``fw``
    reaches, each with the runtime functions that reach it; empty for a single-precision build."""
    return {k: v for k, v in reached_routines(fw).items() if SOFT_ROUTINE.match(k)}


def _models_asm(files: Sequence[Path], offset: int, guard: Path | None = None, faults: Path | None = None) -> str:
    """The model files in flash (``.rodata``), each on an 8-byte boundary plus ``offset``; and the
    envelope file ``guard`` and the faults file ``faults`` on 8-byte boundaries (``tb_guard_file``,
    ``tb_guard_bytes``, ``tb_faults_file``, ``tb_faults_bytes``: 0 without; in sections of their own,
    which an image that does not read them drops)."""
    lines = ['    .section .rodata.tb_models,"a"']
    for i, f in enumerate(files):
        lines += ["    .balign 8", *([f"    .space {offset}"] if offset else []), f"tb_file_{i}:",
                  f'    .incbin "{Path(f).resolve()}"', f"tb_file_{i}_end:"]  # fmt: skip
    if guard is not None:
        lines += ["    .balign 8", "tb_guard_0:", f'    .incbin "{Path(guard).resolve()}"', "tb_guard_0_end:"]
    if faults is not None:
        lines += ["    .balign 8", "tb_faults_0:", f'    .incbin "{Path(faults).resolve()}"', "tb_faults_0_end:"]
    lines += ['    .section .rodata.tb_index,"a"', "    .balign 4", "    .global tb_files", "tb_files:",
              *[f"    .word tb_file_{i}" for i in range(len(files))], "    .global tb_file_bytes", "tb_file_bytes:",
              *[f"    .word tb_file_{i}_end - tb_file_{i}" for i in range(len(files))], "    .global tb_n_files",
              "tb_n_files:", f"    .word {len(files)}",
              '    .section .rodata.tb_guard_index,"a"', "    .balign 4", "    .global tb_guard_file", "tb_guard_file:",
              f"    .word {'tb_guard_0' if guard is not None else 0}", "    .global tb_guard_bytes", "tb_guard_bytes:",
              f"    .word {'tb_guard_0_end - tb_guard_0' if guard is not None else 0}",
              '    .section .rodata.tb_faults_index,"a"', "    .balign 4", "    .global tb_faults_file", "tb_faults_file:",
              f"    .word {'tb_faults_0' if faults is not None else 0}", "    .global tb_faults_bytes", "tb_faults_bytes:",
              f"    .word {'tb_faults_0_end - tb_faults_0' if faults is not None else 0}", ""]  # fmt: skip
    return "\n".join(lines)


def _sized(elf: Path) -> Firmware:
    out = _run(["arm-none-eabi-size", "-A", elf], "arm-none-eabi-size")
    sec = {}
    for ln in out.splitlines():
        parts = ln.split()
        if len(parts) >= 2 and parts[1].isdigit():
            sec[parts[0]] = int(parts[1])
    text = sec.get(".text", 0) + sec.get(".ARM.exidx", 0)
    return Firmware(elf, text, sec.get(".data", 0), sec.get(".bss", 0))


def run(fw: Firmware, samples_text: str, queries_text: str, timeout_s: float = 600.0) -> tuple[list[str], str, list[str]]:
    """Run ``fw`` on QEMU's mps2-an386 (Cortex-M4F, ``-icount shift=fw.icount_shift``: one
    instruction per 2^shift virtual ns) with ``samples.txt`` and ``queries.txt`` in its semihosting
    directory; returns (the query lines, the END line, the COUNT lines: instructions and stack per
    runtime call, and the INFO line: the target's sizes of the runtime's structures, the probes taken)."""
    with tempfile.TemporaryDirectory(prefix="tb_target_") as tmp:
        Path(tmp, "samples.txt").write_text(samples_text)
        Path(tmp, "queries.txt").write_text(queries_text)
        try:
            res = _qemu(fw.elf, cwd=tmp, timeout_s=timeout_s, icount=True, shift=fw.icount_shift)
        except subprocess.TimeoutExpired:
            raise RuntimeFailed(f"the firmware did not finish within {timeout_s:.0f} s on QEMU ({fw.elf})") from None
    lines = res.stdout.splitlines()
    end = next((ln for ln in reversed(lines) if ln.startswith("END ")), None)
    if res.returncode != 0 or end is None:
        raise RuntimeFailed(f"the firmware stopped (QEMU exit {res.returncode}): {(res.stdout + res.stderr).strip()[-2000:]}")
    info = ("COUNT ", "INFO ")
    return [ln for ln in lines if ln and not ln.startswith(("END ", *info))], end, [ln for ln in lines if ln.startswith(info)]


def replay(files: Sequence[Path], samples: pd.DataFrame, temps: Sequence[str], queries: pd.DataFrame,
           precision: str = "double", arena_bytes: int = 16384, live: bool = False, probes: pd.DataFrame | None = None,
           probe_params=None, guard: Path | None = None, faults: Path | None = None,
           **build_kw) -> tuple[pd.DataFrame, dict]:  # fmt: skip
    """:func:`thermbench.export.runtime.replay` on the target: the predictions (``t_s``, ``axis_mm``,
    ``thermal_um``, ``total_um``, ``label``, ``rc``; with ``probe_params``, ``corrected_um`` and
    ``var_um2``: the probe readings ``probes`` correct the model by ``tb_probe``; with ``guard``, an
    envelope file linked into flash, ``distance``: ``tb_guard``'s at the last sample before each
    query, which needs ``live``; with ``faults``, a faults file linked into flash,
    :data:`~thermbench.export.runtime.FAULT_COLUMNS` as ``tb_replay --faults`` gives them, which
    needs ``live``) and what the run reports (``rc``, ``stack_bytes``, ``arena_bytes``,
    ``flash_bytes``, ``ram_bytes``; per operation ``<what>_calls``, ``_insn_mean``, ``_insn_max`` and
    ``_stack_bytes``, ``what`` one of step, predict, open, calibrate, finish, probe_update,
    probe_correct, guard_step, faults_step, faults_bound; ``sizeof_tb_model``, ``sizeof_tb_probe_state``, ``sizeof_tb_guard``
    ... on the target; ``probes_taken``, ``probes_skipped``). ``build_kw``: :func:`build`'s."""
    if (guard is not None or faults is not None) and not live:
        raise ValueError("replay: a guard or a faults file answers live (live=True)")
    fw = build(files, precision, arena_bytes, guard=guard, faults=faults, **build_kw)
    text = stream_text(samples, temps, queries, probes if probe_params is not None else None)
    head = ["L"] if live else []
    if probe_params is not None:
        head.append("F " + " ".join(repr(float(v)) for v in (probe_params.q_bias_um2_per_h, probe_params.q_gain_per_h,
                                                             probe_params.r_um2, probe_params.bias0_um, probe_params.gain0)))  # fmt: skip
    q = "".join(ln + "\n" for ln in [*head, *(ln for ln in text.splitlines() if ln.startswith(("Q", "P")))])
    s = "".join(ln + "\n" for ln in text.splitlines() if ln.startswith("S"))
    lines, end, counts = run(fw, s, q)
    parts = end.split()
    rep = {"rc": int(parts[1]), "stack_bytes": int(parts[2]), "arena_bytes": int(parts[3]),
           "flash_bytes": fw.flash_bytes, "ram_bytes": fw.data_bytes + fw.bss_bytes, "end": end}  # fmt: skip
    for ln in counts:
        if ln.startswith("INFO "):  # key value ...
            kv = ln.split()[1:]
            rep.update({k: int(v) for k, v in zip(kv[::2], kv[1::2])})
            continue
        # COUNT what n sum max stack: instructions per runtime call, the deepest stack of its calls
        _, what, n, total, most, stack = ln.split()
        rep[f"{what}_calls"], rep[f"{what}_insn_mean"], rep[f"{what}_insn_max"] = int(n), float(total) / max(int(n), 1), int(most)
        rep[f"{what}_stack_bytes"] = int(stack)
    cols = {**runtime.REPLAY_COLUMNS, **({"corrected_um": float, "var_um2": float} if probe_params is not None else {}),
            **({"distance": float} if guard is not None else {}), **(runtime.FAULT_COLUMNS if faults is not None else {})}  # fmt: skip
    df = pd.DataFrame([ln.split() for ln in lines], columns=list(cols)).astype(cols)
    return df, rep
