"""The C runtime in-process (ctypes): a live compensator steps the model one control cycle at a time.

:class:`LiveModel` opens an export directory (one model or a per-condition bank) in the
shared library :func:`.runtime.build_shared` compiles (once per process, cached by source
hash), exactly as ``tb_replay`` does from a file: the model files stay in buffers this
object keeps alive (the runtime parses them in place), the running state lives in
16-byte-aligned arenas of ``tb_model_arena_bytes``. Every number comes from the C code;
nothing of the models is computed here. Per control cycle::

    live = LiveModel(export_dir)
    rc = live.step(t_s, axis_mm, feed_mm_min, temps_C)      # temps_C in live.temperatures order
                                                            # (+ operating=[...] in live.operating order)
    rc, thermal_um, total_um, label = live.predict(t_s, axis_mm)  # compensation = -total_um

Runtime codes are returned, never raised (a compensator skips a refused sample and goes
on); only files the runtime refuses raise :class:`~.encoding.ExportError`. Timing (see
``tb_runtime.h``): a value at time t is final once :attr:`LiveModel.ready_s` >= t; it may
be asked up to a horizon past it (the state held), and only as far back as the short
history the runtime keeps (``TB_E_LATE`` beyond). One object is not thread-safe.
"""

from __future__ import annotations

import ctypes
import functools
import math
from pathlib import Path
from typing import Sequence

import numpy as np

from . import runtime
from .directory import read_manifest
from .encoding import ExportError

# tb_runtime.h
TB_MAX_DIMS = 8
TB_MAX_CONDITIONS = 64
TB_OK = 0
TB_E_SIZE, TB_E_MAGIC, TB_E_VERSION, TB_E_KIND, TB_E_CRC = -1, -2, -3, -4, -5
TB_E_DIMS, TB_E_NAN, TB_E_PAYLOAD, TB_E_ARENA, TB_E_STATE = -6, -7, -8, -9, -10
TB_E_INPUT, TB_E_SAMPLING, TB_E_LATE, TB_E_NOTREADY, TB_E_ARG, TB_E_ALIGN = -11, -12, -13, -14, -15, -16
ARENA_ALIGN = 16


class tb_sample(ctypes.Structure):
    _fields_ = [("t_s", ctypes.c_double), ("axis_mm", ctypes.c_double), ("feed_mm_min", ctypes.c_double),
                ("load_N", ctypes.c_double), ("temps_C", ctypes.POINTER(ctypes.c_double)),
                ("n_temps", ctypes.c_uint32), ("measuring", ctypes.c_int)]  # fmt: skip


class tb_model(ctypes.Structure):
    _fields_ = [("payload", ctypes.POINTER(ctypes.c_uint8)), ("n_payload", ctypes.c_uint32),
                ("kind", ctypes.c_uint16), ("dims", ctypes.c_uint32 * TB_MAX_DIMS), ("off", ctypes.c_uint32 * 10),
                ("n_sensors", ctypes.c_uint32), ("max_channel", ctypes.c_uint32), ("state", ctypes.c_void_p),
                ("state_bytes", ctypes.c_size_t)]  # fmt: skip


class tb_bank(ctypes.Structure):
    _fields_ = [("classifier", ctypes.POINTER(tb_model)), ("members", ctypes.POINTER(tb_model) * TB_MAX_CONDITIONS),
                ("n_members", ctypes.c_uint32)]  # fmt: skip


class tb_probe_params(ctypes.Structure):
    _fields_ = [("q_bias_um2_per_h", ctypes.c_double), ("q_gain_per_h", ctypes.c_double), ("r_um2", ctypes.c_double),
                ("bias0_um", ctypes.c_double), ("gain0", ctypes.c_double)]  # fmt: skip


class tb_probe_state(ctypes.Structure):
    _fields_ = [("p", tb_probe_params), ("bias_um", ctypes.c_double), ("gain", ctypes.c_double),
                ("P00", ctypes.c_double), ("P01", ctypes.c_double), ("P11", ctypes.c_double), ("t_s", ctypes.c_double),
                ("n_probes", ctypes.c_uint32)]  # fmt: skip


_M, _B = ctypes.POINTER(tb_model), ctypes.POINTER(tb_bank)
_PS = ctypes.POINTER(tb_probe_state)
_D, _I32 = ctypes.POINTER(ctypes.c_double), ctypes.POINTER(ctypes.c_int32)
_SIGNATURES = {  # name: (restype, argtypes)
    "tb_strerror": (ctypes.c_char_p, [ctypes.c_int]),
    "tb_model_open": (ctypes.c_int, [_M, ctypes.POINTER(ctypes.c_uint8), ctypes.c_size_t]),
    "tb_model_arena_bytes": (ctypes.c_size_t, [_M]),
    "tb_model_start": (ctypes.c_int, [_M, ctypes.c_void_p, ctypes.c_size_t]),
    "tb_model_step": (ctypes.c_int, [_M, ctypes.POINTER(tb_sample)]),
    "tb_model_ready_s": (ctypes.c_double, [_M]),
    "tb_model_predict": (ctypes.c_int, [_M, ctypes.c_double, ctypes.c_double, _D, _D]),
    "tb_bank_init": (ctypes.c_int, [_B, _M, ctypes.POINTER(_M), ctypes.c_uint32]),
    "tb_bank_step": (ctypes.c_int, [_B, ctypes.POINTER(tb_sample)]),
    "tb_bank_ready_s": (ctypes.c_double, [_B]),
    "tb_bank_predict": (ctypes.c_int, [_B, ctypes.c_double, ctypes.c_double, _D, _D, _I32]),
    "tb_probe_init": (ctypes.c_int, [_PS, ctypes.POINTER(tb_probe_params), ctypes.c_double]),
    "tb_probe_correct": (ctypes.c_int, [_PS, ctypes.c_double, ctypes.c_double, _D, _D]),
    "tb_probe_update": (ctypes.c_int, [_PS, ctypes.c_double, ctypes.c_double, ctypes.c_double, _D]),
}


@functools.lru_cache(maxsize=None)
def library() -> ctypes.CDLL:
    """The runtime as a shared library, built (:func:`.runtime.build_shared`) and loaded once per process."""
    lib = ctypes.CDLL(str(runtime.build_shared()))
    for name, (restype, argtypes) in _SIGNATURES.items():
        fn = getattr(lib, name)
        fn.restype, fn.argtypes = restype, argtypes
    return lib


class LiveModel:
    """An export directory (single model or per-condition bank) running in the C runtime in-process."""

    def __init__(self, model_dir, variant: str = "model"):
        self.model_dir = Path(model_dir)
        self.manifest: dict = read_manifest(self.model_dir)
        man = self.manifest
        self.temperatures: list[str] = list(man["temperatures"])
        # operating inputs without a tb_sample field (e.g. spindle_rpm): input channels after the temperatures
        self.operating: list[str] = list(man.get("operating", []))
        self.needs_load: bool = bool(man.get("needs_load", False))
        self.period_s: float = float(man["sample_period_s"])
        self.is_bank: bool = man["kind"] == "bank"
        if self.is_bank:
            names = [man["bank"]["classifier"], *[m["file"] for m in man["bank"]["members"]]]
        else:
            f = man["files"].get(variant)
            if f is None:
                raise ExportError(f"{self.model_dir}: no file variant {variant!r}; it has {sorted(man['files'])}")
            names = [f["file"]]
        self._names = names
        self._lib = library()
        self._files: list = []  # the file bytes: the runtime's models point into them
        self._arenas: list = []  # (buffer kept alive, aligned address, bytes)
        self._models: list[tb_model] = []
        for name in names:
            path = self.model_dir / name
            try:
                data = path.read_bytes()
            except OSError as exc:
                raise ExportError(f"{path}: cannot read the model file ({exc})") from None
            buf = (ctypes.c_uint8 * max(len(data), 1))()
            ctypes.memmove(buf, data, len(data))
            m = tb_model()
            rc = self._lib.tb_model_open(ctypes.byref(m), buf, len(data))
            if rc != TB_OK:
                raise ExportError(f"{path}: the C runtime refuses the file: error {rc}: {self.strerror(rc)}")
            need = self._lib.tb_model_arena_bytes(ctypes.byref(m))
            raw = (ctypes.c_uint8 * (need + ARENA_ALIGN))()
            at = ctypes.addressof(raw)
            self._files.append(buf)
            self._arenas.append((raw, at + (-at) % ARENA_ALIGN, need))
            self._models.append(m)
        if self.is_bank:
            self._bank = tb_bank()
            n = len(self._models) - 1
            self._members = (_M * max(n, 1))(*[ctypes.pointer(m) for m in self._models[1:]])
            self._n_members = n
        self._sample = tb_sample()
        self._temps = (ctypes.c_double * max(len(self.temperatures), 1))()
        self._th, self._tot, self._lab = ctypes.c_double(), ctypes.c_double(), ctypes.c_int32()
        self.start()

    def start(self) -> None:
        """(Re)start: every model from a fresh state (the next sample is the run's first, its
        temperatures the dT baseline); after a long outage, or for a new run."""
        for name, m, (_, at, need) in zip(self._names, self._models, self._arenas):
            rc = self._lib.tb_model_start(ctypes.byref(m), ctypes.c_void_p(at), need)
            if rc != TB_OK:
                raise ExportError(f"{self.model_dir / name}: cannot start: error {rc}: {self.strerror(rc)}")
        if self.is_bank:
            rc = self._lib.tb_bank_init(ctypes.byref(self._bank), ctypes.byref(self._models[0]), self._members,
                                        self._n_members)  # fmt: skip
            if rc != TB_OK:
                msg = f"error {rc}: {self.strerror(rc)}"
                raise ExportError(f"{self.model_dir}: the C runtime refuses the bank: {msg}")

    def step(self, t_s: float, axis_mm: float, feed_mm_min: float, temps_C: Sequence[float], load_N: float = 0.0,
             measuring: bool = False, operating: Sequence[float] = ()) -> int:  # fmt: skip
        """One control cycle (one process-log sample); ``temps_C`` in :attr:`temperatures` order,
        ``operating`` in :attr:`operating` order (e.g. the spindle speed of a lumped network).
        Returns the runtime's code: 0, or e.g. ``TB_E_INPUT`` / ``TB_E_SAMPLING`` for a sample it
        refuses (nothing changes then; the next sample is taken as usual). After a gap longer than
        ``TB_MAX_GAP_S`` (60 s) every sample is ``TB_E_SAMPLING``: :meth:`start` again."""
        vals = [*temps_C, *operating]
        n = len(vals)
        if n > len(self._temps):
            self._temps = (ctypes.c_double * n)()
        self._temps[:n] = [float(v) for v in vals]
        s = self._sample
        s.t_s, s.axis_mm, s.feed_mm_min, s.load_N = float(t_s), float(axis_mm), float(feed_mm_min), float(load_N)
        s.temps_C = self._temps
        s.n_temps = n
        s.measuring = 1 if measuring else 0
        if self.is_bank:
            return self._lib.tb_bank_step(ctypes.byref(self._bank), ctypes.byref(s))
        return self._lib.tb_model_step(ctypes.byref(self._models[0]), ctypes.byref(s))

    def predict(self, t_s: float, axis_mm: float) -> tuple[int, float, float, int]:
        """``(rc, thermal_um, total_um, label)`` at ``t_s`` and ``axis_mm``; compensation = -total_um.
        ``label``: the bank's condition index in force (-1: none yet, or not a bank); on rc != 0
        the errors are NaN and the label -1."""
        th, tot, lab = self._th, self._tot, self._lab
        lab.value = -1
        if self.is_bank:
            rc = self._lib.tb_bank_predict(ctypes.byref(self._bank), float(t_s), float(axis_mm), ctypes.byref(th),
                                           ctypes.byref(tot), ctypes.byref(lab))  # fmt: skip
        else:
            rc = self._lib.tb_model_predict(ctypes.byref(self._models[0]), float(t_s), float(axis_mm),
                                            ctypes.byref(th), ctypes.byref(tot))  # fmt: skip
        if rc != TB_OK:
            return rc, math.nan, math.nan, -1
        return rc, th.value, tot.value, lab.value

    def predict_many(self, t_s: float, axis_mm) -> tuple[np.ndarray, np.ndarray]:
        """The positioning error over many positions at one time (the error line over the
        travel): ``(rc, total_um)`` arrays, total NaN where rc != 0."""
        xs = np.asarray(axis_mm, dtype=float).ravel()
        rc = np.empty(xs.size, dtype=int)
        tot = np.empty(xs.size, dtype=float)
        for i, x in enumerate(xs):
            rc[i], _, tot[i], _ = self.predict(t_s, x)
        return rc, tot

    @property
    def ready_s(self) -> float:
        """The time up to which the runtime's values are final (-1e30 before the first ones)."""
        if self.is_bank:
            return self._lib.tb_bank_ready_s(ctypes.byref(self._bank))
        return self._lib.tb_model_ready_s(ctypes.byref(self._models[0]))

    @staticmethod
    def strerror(rc: int) -> str:
        """The runtime's message for a code (``tb_strerror``)."""
        return library().tb_strerror(int(rc)).decode()

    def __repr__(self) -> str:
        kind = "bank" if self.is_bank else self.manifest["kind"]
        return f"LiveModel({str(self.model_dir)!r}, {kind}, temperatures={self.temperatures})"


class LiveProbe:
    """The C runtime's probe filter (``tb_probe_*``, embedded/src/tb_probe.c) in-process: corrects a
    model's total error from probe readings (:mod:`thermbench.bench.adapt` for the model of it). ``params``:
    a :class:`thermbench.bench.adapt.ProbeParams`; the filter starts at ``t0_s``. Codes are returned, never
    raised (a probe older than the state: ``TB_E_LATE``)."""

    STATE_FIELDS = ("bias_um", "gain", "P00", "P01", "P11", "t_s", "n_probes")

    def __init__(self, params, t0_s: float) -> None:
        self._lib = library()
        self.params = params
        self._st = tb_probe_state()
        p = tb_probe_params(*(float(getattr(params, f)) for f, _ in tb_probe_params._fields_))
        rc = self._lib.tb_probe_init(ctypes.byref(self._st), ctypes.byref(p), float(t0_s))
        if rc != TB_OK:
            raise ExportError(f"the C runtime refuses the probe filter's parameters {params}: error {rc}")
        self._v, self._var = ctypes.c_double(), ctypes.c_double()

    def correct(self, t_s: float, predicted_um: float) -> tuple[int, float, float]:
        """``(rc, corrected_um, var_um2)`` of the model's total ``predicted_um`` at ``t_s``."""
        rc = self._lib.tb_probe_correct(ctypes.byref(self._st), float(t_s), float(predicted_um), ctypes.byref(self._v),
                                        ctypes.byref(self._var))  # fmt: skip
        return (rc, self._v.value, self._var.value) if rc == TB_OK else (rc, math.nan, math.nan)

    def probe(self, t_s: float, predicted_um: float, measured_um: float) -> tuple[int, float]:
        """Take a reading (``predicted_um``: the model's uncorrected total at its time and place);
        ``(rc, innovation_um)``."""
        rc = self._lib.tb_probe_update(ctypes.byref(self._st), float(t_s), float(predicted_um), float(measured_um),
                                       ctypes.byref(self._v))  # fmt: skip
        return rc, (self._v.value if rc == TB_OK else math.nan)

    @property
    def t_s(self) -> float:
        return self._st.t_s

    @property
    def n_probes(self) -> int:
        return int(self._st.n_probes)

    def state(self) -> dict:
        """The filter's state (with :meth:`restore`: a warm restart goes on with it)."""
        return {f: (int(getattr(self._st, f)) if f == "n_probes" else float(getattr(self._st, f))) for f in self.STATE_FIELDS}

    def restore(self, state: dict) -> None:
        for f in self.STATE_FIELDS:
            setattr(self._st, f, int(state[f]) if f == "n_probes" else float(state[f]))
