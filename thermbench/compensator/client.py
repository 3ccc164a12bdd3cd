"""``thermbench compensator MODEL_DIR --endpoint opc.tcp://HOST:PORT --nodes nodes.yaml``.

An OPC UA client (asyncua) beside the machine, the role of seed 002's STM32
compensator (§2.5, Fig. 14: it reads the CNC's axis state and temperatures and writes
the compensation back over OPC UA). Every cycle (``period_s`` of the client's clock,
scheduled on absolute deadlines so the cycle never drifts) it

1. reads the input nodes of ``nodes.yaml`` in one request (values and source timestamps);
2. runs :class:`~thermbench.compensator.control.CycleLogic`: input guard, the exported
   model stepped in the C runtime (:class:`thermbench.export.native.LiveModel`), rate limit;
3. writes the compensation, as the value at the current position and/or the error line
   (offset, slope, reference position) a stock controller takes, and the status flags;
4. appends one line to the cycle log (CSV, flushed every cycle).

A lost connection is retried in the background with exponential back-off while the
cycles go on, flagged ``DISCONNECTED`` with the compensation held at its last good value
(written again as soon as the server is back). Writes go through :class:`.opcua.GuardedWriter`,
which refuses any node but the configured outputs.

Security: user name and password (the password from an environment variable, never
from a file), and ``Basic256Sha256`` sign-and-encrypt with the client's certificate and
the server certificate it pins (``thermbench certs`` makes self-signed pairs).
"""

from __future__ import annotations

import asyncio
import collections
import json
import math
import time
from pathlib import Path
from typing import Any, Callable, Mapping

import numpy as np

from ..outputs import check_output_file, write_text
from .control import TB_MAX_GAP_S, CycleLogic, Flags
from .cyclelog import STATS_CYCLES, CycleLog, Ring, cycle_stats, status_line
from .deadlines import Deadlines
from .errors import CompensatorError
from .nodes import load_nodes
from .opcua import (NOT_CERTIFICATES, Security, Session, _connection_errors, _ua, explain_security_refusal, output_variants,
                    resume_from_controller)  # fmt: skip
from .settings import Settings, _num
from .state import StateError, StateStore


class Compensator:
    """The control loop (see the module docstring); :meth:`run` returns the summary."""

    def __init__(self, model_dir: str | Path, endpoint: str, nodes_path: str | Path, cfg: Mapping[str, Any],
                 say: Callable[[str], None] | None = None) -> None:
        """``say``: where ``connected``, the status lines (every ``status_every_s``) and the
        reconnections go (the command prints them; None: silent)."""
        from ..config import with_defaults
        from ..export.native import LiveModel

        cfg = with_defaults("compensator", cfg)
        self.period_s = _num(cfg, "period_s", 0.1)
        self.output = str(cfg.get("output", "value"))
        self.model = LiveModel(model_dir)
        self.nodes = load_nodes(nodes_path, self.model.temperatures, self.model.needs_load, self.output,
                                getattr(self.model, "operating", []))  # fmt: skip
        self.logic = CycleLogic(self.model, Settings.from_config(cfg), self.output, has_load=self.model.needs_load,
                                has_measuring=self.nodes.inputs.measuring is not None)  # fmt: skip
        self.sec = Security.from_config(cfg.get("security"))
        self.endpoint = endpoint
        self.timeout_s = _num(cfg, "timeout_s", 2.0)
        rc = dict(cfg.get("reconnect") or {})
        self.backoff0 = _num(rc, "initial_s", 0.2, name="reconnect.initial_s")
        self.backoff_max = _num(rc, "max_s", 10.0, name="reconnect.max_s")
        self.backoff_factor = _num(rc, "factor", 2.0, name="reconnect.factor")
        if self.backoff_factor < 1 or self.backoff_max < self.backoff0:
            raise CompensatorError("config key 'reconnect': expected factor >= 1 and max_s >= initial_s, got "
                                   f"factor {self.backoff_factor}, initial_s {self.backoff0}, max_s {self.backoff_max}")  # fmt: skip
        max_cycles = None if cfg.get("max_cycles") is None else _num(cfg, "max_cycles", 1)
        if max_cycles is not None and (not math.isfinite(max_cycles) or max_cycles != int(max_cycles)):
            raise CompensatorError(f"config key 'max_cycles': expected null or a whole number > 0, got {max_cycles}")
        self.max_cycles = None if max_cycles is None else int(max_cycles)
        self.duration_s = None if cfg.get("duration_s") is None else _num(cfg, "duration_s", 1.0)
        self.status_every_s = _num(cfg, "status_every_s", 5.0)
        self.say = say
        self.log_path = Path(str(cfg.get("log", "compensator_log.csv")))
        check_output_file(self.log_path, "compensator-log")  # refused before anything connects
        check_output_file(self.log_path.with_suffix(".summary.json"), "compensator-summary")
        st = dict(cfg.get("state") or {})
        self.state_every_s = _num(st, "every_s", 5.0, name="state.every_s")
        self.state_max_gap_s = _num(st, "max_gap_s", 60.0, name="state.max_gap_s")
        self.state_agree_C = _num(st, "agree_C", 2.0, name="state.agree_C")
        self.state_history = bool(st.get("history", True))
        if self.state_max_gap_s > TB_MAX_GAP_S:
            raise CompensatorError(f"config key 'state.max_gap_s': at most {TB_MAX_GAP_S:g} s (the longest gap the C "
                                   f"runtime bridges), got {self.state_max_gap_s:g}")  # fmt: skip
        self.store = StateStore(str(st["path"])) if st.get("path") else None
        self.logic.keep_stepped = self.store is not None
        try:
            self.saved_state = self.store.load() if self.store is not None else None
        except StateError as exc:
            raise CompensatorError(str(exc)) from None
        self.resume_pending = self.store is not None
        self._flag_next = 0  # a flag for the next cycle (RESUMED)
        self.session = Session(endpoint, self.nodes, self.sec, self.timeout_s)
        self.stop_requested = False
        self.stop_reason = "stopped"
        self.connect_attempts: collections.deque = collections.deque(maxlen=1000)  # loop times of reconnection attempts
        self.last_error: str | None = None
        self.summary: dict | None = None

    def _say(self, line: str) -> None:
        if self.say is not None:
            self.say(line)

    def _resume_from_controller(self) -> None:
        """Ramp from what the controller holds (read when the session opened), not from zero."""
        resume_from_controller(self.logic, self.session.current, self.nodes)

    async def run(self) -> dict:
        """Connect (the first connection must succeed: a wrong endpoint or credentials are a
        set-up error), then cycle until done / max_cycles / duration_s / :meth:`stop`. The
        summary is written beside the log however the loop ends (also on Ctrl-C)."""
        try:
            log = CycleLog(self.log_path, self.logic.names)
        except OSError as exc:
            raise CompensatorError(f"config key 'log': cannot write {self.log_path}: {exc.strerror or exc}") from None
        try:
            await self.session.open()
        except CompensatorError:
            log.close()
            raise
        except Exception as exc:
            log.close()
            code = type(exc).__name__ if isinstance(exc, _ua().UaStatusCodeError) else None
            certificates = code not in NOT_CERTIFICATES  # stacks report a certificate refusal in many ways
            why = await explain_security_refusal(self.endpoint, self.session.sec, self.session.timeout_s) if certificates else None
            if why and code:
                why = f"{why} ({code})"
            raise CompensatorError(f"cannot connect to {self.endpoint}: {why or f'{type(exc).__name__}: {exc}'}") from None
        self._resume_from_controller()
        self._say(f"connected to {self.endpoint}: {len(self.session.inputs)} inputs, outputs "
                  f"{', '.join(self.nodes.output_ids())}")  # fmt: skip
        loop = asyncio.get_running_loop()
        durations, lates, starts, index = (Ring(STATS_CYCLES) for _ in range(4))
        window: list[float] = []  # cycle times since the last status line
        next_status = loop.time() + self.status_every_s
        next_state = loop.time() + self.state_every_s
        counts = collections.Counter()
        connecting: asyncio.Task | None = None
        backoff, next_try = self.backoff0, 0.0
        sched = Deadlines(self.period_s, loop.time(), self.max_cycles, self.duration_s)
        ended = None
        task = asyncio.current_task()
        try:
            while not self.stop_requested:
                if getattr(task, "cancelling", lambda: 0)():  # a cancellation some library call swallowed
                    raise asyncio.CancelledError
                k, deadline = sched.k, sched.deadline
                wait = sched.wait_s(loop.time())
                if wait > 0:
                    await asyncio.sleep(wait)
                begin = loop.time()
                done = False
                if connecting is not None and connecting.done():  # a reconnection attempt has ended
                    exc = connecting.exception()
                    connecting = None
                    if exc is None:
                        self._say(f"reconnected to {self.endpoint}")
                        counts["reconnects"] += 1
                        self.logic.reconnected()
                        self._resume_from_controller()  # a restarted controller may hold another value
                    else:
                        self.last_error = f"reconnecting: {type(exc).__name__}: {exc}"
                        next_try = begin + backoff
                        backoff = min(backoff * self.backoff_factor, self.backoff_max)
                if self.session.client is None and connecting is None and begin >= next_try:
                    connecting = asyncio.ensure_future(self.session.open())
                    self.connect_attempts.append(begin)
                if self.session.client is None:
                    c = self.logic.hold(Flags.DISCONNECTED)
                else:
                    c = None
                    try:
                        readings = await self.session.read()
                        if self.resume_pending:
                            await self._resume_or_cold(readings, begin)
                        c = self.logic.cycle(readings, begin, time.time())
                        c.flags, self._flag_next = int(c.flags | self._flag_next), 0
                        await self.session.write(output_variants(c, self.nodes, self.output))
                        done = bool(readings.get("done") and readings["done"].value)
                        backoff = self.backoff0  # a full cycle worked: the next outage starts the back-off afresh
                    except _connection_errors() as exc:
                        counts["connection_lost"] += 1
                        self.last_error = f"{type(exc).__name__}: {exc}"
                        self.logic.undo()  # what this cycle computed was not written
                        await self.session.close()
                        next_try = loop.time() + backoff
                        c = self.logic.hold(Flags.DISCONNECTED, c.t_s if c is not None else math.nan)
                end = loop.time()
                cyc_ms, late_ms = 1e3 * (end - begin), 1e3 * (begin - deadline)
                durations.append(cyc_ms)
                lates.append(late_ms)
                starts.append(begin)
                index.append(k)
                for f in Flags:
                    if f.value and c.flags & f.value:
                        counts[f.name] += 1
                if c.flags & Flags.RESTARTED:
                    self._say(f"COLD RESTART at machine time {c.t_s:.0f} s: the model restarted (a gap longer than the "
                              "runtime bridges, or the server's clock restarted); it starts from the machine as it is "
                              "now (flag COLD from here on)")  # fmt: skip
                if self.store is not None and end >= next_state:
                    self._save_state()
                    next_state = end + self.state_every_s
                log.write(time.time(), k, c, late_ms, cyc_ms)
                window.append(cyc_ms)
                if end >= next_status:
                    self._say(status_line(k, c, window))
                    window.clear()
                    next_status = end + self.status_every_s
                over = sched.next(end)
                if done:
                    ended = "the machine's program is done"
                    break
                if over:
                    ended = over
                    break
        except asyncio.CancelledError:
            ended = "interrupted"
            raise
        except BaseException as exc:
            ended = f"error: {type(exc).__name__}: {exc}"
            raise
        finally:
            log.close()
            if self.store is not None and not self.resume_pending:
                self._save_state()
                self.store.close()
            if connecting is not None:
                connecting.cancel()
            await self.session.close()
            if sched.skipped:
                counts["skipped_deadlines"] = sched.skipped
            self.summary = {"endpoint": self.endpoint, "model": self.model.manifest.get("name"), "period_s": self.period_s,
                            "output": self.output, "log": str(self.log_path), "ended": ended or self.stop_reason, "flags": dict(counts),
                            "last_error": self.last_error,
                            **cycle_stats(durations.values(), lates.values(), index.values(), starts.values(), self.period_s)}  # fmt: skip
            write_text(self.log_path.with_suffix(".summary.json"), json.dumps(self.summary, indent=2, default=float) + "\n",
                       "compensator-summary")
        return self.summary

    def _save_state(self) -> None:
        self.store.sync(self.logic.stepped, self.logic.starts)
        self.store.save({**self.logic.state(), "model": self.model.manifest.get("name"), "saved_utc": time.time()})

    async def _resume_or_cold(self, readings, now_wall_s: float) -> None:
        """At the first reading: go on from the saved state (warm), replay an outage longer than
        the runtime bridges from the server's history (OPC UA Historical Access) when it keeps one,
        or start cold; saying which."""
        self.resume_pending = False
        saved = self.saved_state
        if saved is None:  # the first start: nothing says the machine ran before
            self._say(f"starting fresh: no saved state at {self.store.path} (the machine as it is now is the model's zero)")
            self.store.sync(self.logic.stepped, self.logic.starts)
            return
        state, rows = saved
        ts = self.logic._machine_ts(readings, now_wall_s, time.time())
        now = {n: float(r.value) for n, r in readings.items() if r is not None and isinstance(r.value, (int, float))}
        warm, why = self.logic.resume_decision(state, rows, ts, now, self.state_max_gap_s, self.state_agree_C)
        if not warm and self.state_history and why.startswith("the saved state is ") and "old" in why:
            missed, note = await self._history_rows(state, rows, ts)
            if missed:
                rows = np.vstack([rows, np.asarray(missed, dtype=float)])
                state = {**state, "last_ts": float(state["t0_ts"]) + missed[-1][0] * self.logic.period_s}
                warm, why2 = self.logic.resume_decision(state, rows, ts, now, self.state_max_gap_s, self.state_agree_C)
                why = (f"{why}: the outage replayed from the server's history ({len(missed)} samples), {why2}" if warm
                       else f"{why}; after the server's history: {why2}")  # fmt: skip
            else:
                why = f"{why}, and {note}"
        if warm:
            self.logic.warm_start(state, rows)
            self._resume_from_controller()  # what the controller holds now, if it says, is where the ramp starts
            self._flag_next = Flags.RESUMED
            self._say(f"resumed the model state of {self.store.path}: {why}")
        else:
            self.logic.cold = True
            self._say(f"COLD START: {why}; the model starts from the machine as it is now, and a machine still warm "
                      "from before reads as its zero (flag COLD on every cycle of this run)")  # fmt: skip
        self.store.sync(self.logic.stepped, self.logic.starts)

    async def _history_rows(self, state: dict, rows, ts_now: float) -> tuple[list[tuple], str]:
        """The samples the model missed (grid points after the saved state, before now), from the
        server's raw history of every input (each value held until the next, as the loop holds
        them, from the saved state's last sample on); ([], why not) when the server keeps none or
        its history has a hole longer than the runtime bridges (:func:`history_hole`)."""
        import datetime as dt

        ua = _ua()
        lg = self.logic
        t0, p = float(state["t0_ts"]), lg.period_s
        k_last, k_now = int(rows[-1][0]), math.floor((ts_now - t0) / p + 1e-3)
        if k_now - k_last <= 1:
            return [], "no sample is missing"
        start = dt.datetime.fromtimestamp(float(state["last_ts"]), dt.timezone.utc)
        end = dt.datetime.fromtimestamp(ts_now, dt.timezone.utc)
        series: dict[str, tuple[np.ndarray, list]] = {}
        for name, node in zip(self.session.inputs, self.session.input_nodes):
            if name in ("done", "heartbeat", "probe"):
                continue
            try:
                dvs = await asyncio.wait_for(node.read_raw_history(start, end), 10 * self.timeout_s)
            except (ua.UaStatusCodeError, asyncio.TimeoutError) as exc:
                return [], f"the server keeps no history of {name} ({type(exc).__name__})"
            pts = sorted((dv.SourceTimestamp.timestamp(), dv.Value.Value) for dv in dvs
                         if dv.SourceTimestamp is not None and dv.Value is not None and dv.StatusCode.is_good())  # fmt: skip
            series[name] = (np.array([q[0] for q in pts], dtype=float), [q[1] for q in pts])
        hole = history_hole(float(state["last_ts"]), ts_now, [t for t, _ in series.values()], self.state_max_gap_s)
        if hole:
            return [], hole
        n0 = len(lg.STATE_COLUMNS)
        last = rows[-1]
        held = {"axis_mm": last[1], "feed_mm_min": last[2], "load_N": last[3], "measuring": last[4],
                **{f"{s}_C": last[n0 + j] for j, s in enumerate(lg.model.temperatures)},
                **{o: last[n0 + len(lg.model.temperatures) + j] for j, o in enumerate(lg.operating)}}  # fmt: skip
        out = []
        for k in range(k_last + 1, k_now):
            t = t0 + k * p
            v = dict(held)
            for name, (ts, vals) in series.items():
                i = int(np.searchsorted(ts, t + 1e-3 * p)) - 1  # the grid's tolerance: stamps carry float rounding
                if i >= 0:
                    v[name] = float(vals[i])
            out.append((k, v["axis_mm"], v["feed_mm_min"], v.get("load_N", 0.0), float(bool(v.get("measuring", 0.0))),
                        *[v[f"{s}_C"] for s in lg.model.temperatures], *[v[o] for o in lg.operating]))  # fmt: skip
        return out, ""

    def stop(self, reason: str = "stopped") -> None:
        """End the loop after the current cycle (the summary says ``reason``)."""
        self.stop_reason = reason
        self.stop_requested = True


def history_hole(start_ts: float, end_ts: float, stamps: list[np.ndarray], max_gap_s: float) -> str:
    """Why the server's history of an outage from ``start_ts`` to ``end_ts`` (source timestamps) cannot
    be replayed, or "" when it can. A historian stores a value when it changes (OPC UA's data-change
    historising, a deadband): one input with no point for a while held its value, as the loop would
    have held it (the feed of a long cut, the measuring flag between two probing cycles, for
    minutes). A hole is a time with no point of *any* input for longer than ``max_gap_s``: nothing
    was recorded then, and the inputs are not known."""
    t = np.sort(np.concatenate([[start_ts], *[np.asarray(s, dtype=float) for s in stamps], [end_ts]]))
    t = t[(t >= start_ts) & (t <= end_ts)]
    gaps = np.diff(t)
    if not gaps.size or gaps.max() <= max_gap_s:
        return ""
    i = int(np.argmax(gaps))
    return (f"the server's history has no value of any input for {gaps[i]:.0f} s (from {t[i] - start_ts:.0f} s after the "
            f"saved state), more than the {max_gap_s:.0f} s the runtime bridges")


def run_compensator(model_dir, endpoint: str, nodes_path, cfg: Mapping[str, Any]) -> dict:
    """Plain entry point (the CLI's): run the loop to its end and return the summary."""
    return asyncio.run(Compensator(model_dir, endpoint, nodes_path, cfg).run())


def format_summary(s: dict) -> str:
    if not s.get("cycles"):
        return f"compensator: no cycles ran against {s['endpoint']}"
    c, lt = s["cycle_ms"], s["late_ms"]
    flags = ", ".join(f"{k} {v}" for k, v in sorted(s["flags"].items())) or "none"
    return "\n".join([
        f"compensator {s['model']} -> {s['endpoint']}: {s['cycles']} cycles at {1e3 * s['period_s']:.0f} ms ({s['output']})",
        f"  cycle time p50 {c['p50']:.2f} ms, p90 {c['p90']:.2f} ms, p99 {c['p99']:.2f} ms, max {c['max']:.2f} ms; "
        f"start lateness p50 {lt['p50']:.2f} ms, p99 {lt['p99']:.2f} ms; mean period {s['mean_period_ms']:.3f} ms, "
        f"lateness trend over the run {s['drift_ms']:+.2f} ms",
        f"  flags: {flags}; ended: {s['ended']}" + (f"; last connection error: {s['last_error']}" if s.get("last_error") else ""),
        f"  log -> {s['log']} (summary beside it)",
    ])  # fmt: skip
