"""The C runtime in-process (thermbench.export.native): a live compensator stepping an exported
model one control cycle at a time gives the numbers ``tb_replay`` gives from the same files."""

from __future__ import annotations

import ctypes
import re
import shutil

import numpy as np
import pytest

from thermbench.bench.datasets import load_benchmark
from thermbench.export import ExportError, native, replay_dir, runtime
from thermbench.export.samples import process_samples, readings_queries
from thermbench.export.native import TB_E_INPUT, TB_E_LATE, TB_E_NOTREADY, LiveModel, tb_model

RUN = "valid1"
EXACT_UM = 1e-9  # the same C code on the same doubles


@pytest.fixture(scope="module")
def ds(seed001_data_root):
    return load_benchmark("seed001_vmc_x", seed001_data_root)


@pytest.fixture(scope="module")
def exported(seed001_exports):
    """A single model and a per-condition bank (seed 002 §2.4-2.5, the cheapest member family)."""
    return seed001_exports


@pytest.fixture(scope="module")
def run_log(ds):
    return process_samples(ds, RUN), readings_queries(ds, RUN)


def _stream(live: LiveModel, ds, samples, queries):
    """Step ``live`` through ``samples``; answer each query once the runtime is stepped past it.
    Returns the step codes and per query (rc, thermal_um, total_um, label)."""
    T = samples[[ds.metadata.sensor_column(s) for s in live.temperatures]].to_numpy(dtype=float)
    cols = [samples[c].to_numpy() for c in ("t_s", "axis_mm", "feed_mm_min", "measuring")]
    qt, qx = queries["t_s"].to_numpy(), queries["axis_mm"].to_numpy()
    step_rc, out, j = [], [], 0
    for i, (t, x, f, meas) in enumerate(zip(*cols)):
        step_rc.append(live.step(t, x, f, T[i], measuring=bool(meas)))
        while j < len(qt) and qt[j] <= live.ready_s:
            out.append(live.predict(qt[j], qx[j]))
            j += 1
    assert j == len(qt), "every reading lies within the run's process log"
    return np.array(step_rc), np.array(out)


@pytest.mark.parametrize("name", ["mlr", "bank"])
def test_live_model_reproduces_tb_replay(exported, ds, run_log, name):
    samples, q = run_log
    live = LiveModel(exported / name)
    assert live.is_bank == (name == "bank") and live.temperatures == ["T_nut", "T_bed"]
    assert live.period_s == 1.0 and not live.needs_load
    step_rc, got = _stream(live, ds, samples, q)
    ref = replay_dir(exported / name, ds, RUN, q)
    assert (step_rc == 0).all() and (got[:, 0] == 0).all()
    assert np.max(np.abs(got[:, 2] - ref["total_um"].to_numpy())) < EXACT_UM
    assert np.max(np.abs(got[:, 1] - ref["thermal_um"].to_numpy())) < EXACT_UM
    assert got[:, 3].astype(int).tolist() == ref["label"].tolist()
    if name == "bank":
        assert (got[:, 3] >= 0).any()
    else:
        assert (got[:, 3] == -1).all()
    # start() is a fresh run: the same numbers again
    live.start()
    assert live.ready_s <= -1e30  # "no time yet" (tb_model_ready_s)
    step_rc2, again = _stream(live, ds, samples, q)
    assert (step_rc2 == 0).all()
    np.testing.assert_array_equal(again, got)


@pytest.mark.parametrize("name", ["mlr", "bank"])
def test_predict_many_is_predict_over_the_travel(exported, ds, run_log, name):
    samples, q = run_log
    live = LiveModel(exported / name)
    _stream(live, ds, samples.iloc[:3000], q[q["t_s"] <= samples["t_s"].iloc[2999]])
    t, xs = live.ready_s, np.linspace(0.0, 500.0, 26)
    rc, total = live.predict_many(t, xs)
    loop = [live.predict(t, x) for x in xs]
    assert rc.dtype.kind == "i" and (rc == 0).all()
    np.testing.assert_array_equal(total, [p[2] for p in loop])
    assert np.ptp(total) > 0  # a line over the travel, not a constant
    # past the horizon (no samples for longer than TB_MAX_GAP_S): refused, NaN, not an exception
    rc, total = live.predict_many(t + 3600.0, xs)
    assert (rc == TB_E_NOTREADY).all() and np.isnan(total).all()
    if name == "mlr":  # older than the runtime's short history
        assert live.predict(t - 600.0, 0.0)[0] == TB_E_LATE


@pytest.mark.parametrize("name", ["mlr", "bank"])
def test_bad_sample_is_refused_and_the_model_goes_on(exported, ds, run_log, name):
    """A NaN temperature: TB_E_INPUT returned (no exception), the sample skipped; afterwards the
    model runs on exactly as ``tb_replay --lenient`` over the same log."""
    samples, q = run_log
    bad = samples.copy()
    k = 4000
    bad.loc[bad.index[k], ds.metadata.sensor_column("T_nut")] = np.nan
    live = LiveModel(exported / name)
    step_rc, got = _stream(live, ds, bad, q)
    assert step_rc[k] == TB_E_INPUT == -11 and (np.delete(step_rc, k) == 0).all()
    assert LiveModel.strerror(TB_E_INPUT) == "bad sample"
    assert (got[:, 0] == 0).all()
    ref = replay_dir(exported / name, ds, RUN, q, samples=bad, lenient=True)
    assert np.max(np.abs(got[:, 2] - ref["total_um"].to_numpy())) < EXACT_UM


@pytest.mark.parametrize("name, file", [("mlr", "model.tbm"), ("bank", "member_01.tbm")])
def test_corrupted_file_raises_naming_it(exported, tmp_path, name, file):
    d = tmp_path / name
    shutil.copytree(exported / name, d)
    data = bytearray((d / file).read_bytes())
    data[48 + 5] ^= 0x10  # a payload byte: the CRC-32 no longer matches
    (d / file).write_bytes(bytes(data))
    with pytest.raises(ExportError, match=rf"{file}.*CRC-32 mismatch"):
        LiveModel(d)


def test_structures_match_the_c_runtime(exported):
    """ctypes' tb_model has the size the compiled runtime reports (tb_replay --info); the error
    codes are the header's."""
    inf = runtime.info([exported / "mlr" / "model.tbm", exported / "bank" / "classifier.tbm"])
    assert (inf["model_bytes"] == ctypes.sizeof(tb_model)).all()
    header = (runtime.embedded_dir() / "include" / "tb_runtime.h").read_text()
    codes = {k: int(v) for k, v in re.findall(r"\b(TB_(?:OK|E_\w+)) = (-?\d+)", header)}
    assert len(codes) == 17 and all(getattr(native, k) == v for k, v in codes.items())
    lib = runtime.build_shared()
    assert lib.name.startswith("libtb_runtime-") and lib.suffix == ".so" and lib == runtime.build_shared()
    with pytest.raises(runtime.RuntimeUnavailable, match="no C compiler"):
        runtime.build_shared(cc="no-such-cc-for-thermbench")


EXPF_CHECK = r"""
#include "tb_internal.h"
#include <stdio.h>
int main(void)
{
    double worst = 0;
    long n = 0;
    float x;
    for (x = -87.0f; x < 88.7f; x = nextafterf(x, 100.0f) + 1e-4f * fabsf(x), n++) {
        double ref = exp((double)x), ulp = ldexp(1.0, ilogb(ref) - 23);
        double e = fabs((double)tbi_expf(x) - ref) / ulp;
        if (e > worst) worst = e;
    }
    printf("%ld %.6f %d %d %d %.9g\n", n, worst, isnan(tbi_expf(nanf(""))) != 0, isinf(tbi_expf(100.0f)) != 0,
           tbi_expf(-100.0f) == 0.0f, (double)tbi_expf(0.0f));
    return 0;
}
"""


def test_the_single_precision_exp_is_within_two_ulps_of_exp(tmp_path):
    """The float runtime's own e^x (tb_internal.h, Cody-Waite and a Taylor polynomial: newlib's
    expf costs ~100 instructions on the M4) against the C library's double exp, rounded to
    float32's spacing at the result: within 2 ulps at about 1.9 million points over the whole
    range that is neither 0 nor infinity; NaN stays NaN, the ends saturate, e^0 = 1 exactly."""
    import subprocess

    src = tmp_path / "expf_check.c"
    src.write_text(EXPF_CHECK)
    d = runtime.embedded_dir()
    exe = tmp_path / "expf_check"
    subprocess.run(["gcc", "-std=c99", "-O2", "-DTB_SINGLE", f"-I{d / 'include'}", f"-I{d / 'src'}", str(src), "-o",
                    str(exe), "-lm"], check=True)  # fmt: skip
    n, worst, nan, inf, zero, one = subprocess.run([str(exe)], capture_output=True, text=True, check=True).stdout.split()
    assert int(n) > 1_000_000 and float(worst) <= 2.0
    assert (nan, inf, zero, float(one)) == ("1", "1", "1", 1.0)


def test_the_classifier_s_feed_table_gives_what_a_pass_over_the_window_gives(exported, ds):
    """The classifier keeps a table of the ring's distinct moving feeds (at most 64) as samples come
    and go, so a window needs no pass to find its feeds. Against the runtime built to make that
    pass every time (-DTBI_CLF_SCAN=1, the earlier code): the same condition at every query of a
    log of three loading states (20 min each) with, after the first, 80 feeds in a scrambled order
    (the table overflows: those windows found by the pass) and 40 feeds 5 % apart visited unevenly
    (the table's, inserted anywhere in its order, dropped as they leave the ring)."""
    import pandas as pd

    parts, t = [], 0.0
    for i, run in enumerate(("state1", "state3", "state5")):
        seg = process_samples(ds, run).iloc[:1200].copy()
        seg["t_s"] = seg["t_s"] - seg["t_s"].iloc[0] + t
        parts.append(seg)
        t = float(seg["t_s"].iloc[-1]) + 1.0
        if i == 0:  # the feed stretch
            k = np.arange(700)
            mid = pd.DataFrame({c: np.repeat(seg[c].iloc[-1:].to_numpy(), len(k)) for c in seg.columns})
            mid["t_s"] = t + k
            mid["axis_mm"] = 100.0 + 40.0 * (k % 2)
            j = np.where(k < 350, (37 * k) % 80, np.floor(40 * ((0.618 * k) % 1.0) ** 2))  # scrambled, then uneven
            mid["feed_mm_min"] = np.where(k < 350, 800.0 + 10.0 * j, 500.0 * 1.05**j)
            if "measuring" in mid:
                mid["measuring"] = 0
            parts.append(mid)
            t += len(k)
    log = pd.concat(parts, ignore_index=True)
    q = pd.DataFrame({"t_s": np.arange(30.0, log["t_s"].iloc[-1], 30.0), "axis_mm": 100.0})
    files, _, temps, _ = bundle_inputs(exported / "bank", ds)
    table = runtime.replay(files, log, temps, q, bank=True)
    scan = runtime.replay(files, log, temps, q, bank=True, exe=runtime.build("tb_replay", ["-DTBI_CLF_SCAN=1"]))
    assert (table["rc"] == 0).all() and len(table) == len(q)
    assert table["label"].tolist() == scan["label"].tolist()
    assert table.loc[table["label"] >= 0, "label"].nunique() >= 3  # the states are told apart


def bundle_inputs(model_dir, ds):
    from thermbench.export.directory import replay_inputs

    return replay_inputs(model_dir, ds, RUN)
