"""thermbench.iso230 against hand-computed ISO 230-2 / ISO 230-3 figures on small tables.

Every expected value below is worked out by hand in the comments next to it (small round numbers),
never copied from the code's output. One property test compares positioning_statistics with a
straightforward re-implementation in plain Python loops on seeded random data.
"""

from __future__ import annotations

import math
import re
import statistics

import numpy as np
import pandas as pd
import pytest

from thermbench.iso230 import (
    drift_summary,
    environmental_variation_error,
    error_line,
    error_lines,
    positioning_statistics,
    positioning_statistics_by,
    tilt,
)

NAN = float("nan")


def _table(data: dict[tuple[float, int], list[float]], **extra) -> pd.DataFrame:
    """{(target_mm, direction): [x_i1, x_i2, ...]} -> readings (cycle j = 1, 2, ...)."""
    rows = [
        {"target_mm": target, "direction": direction, "cycle": j, "deviation_um": x, **extra}
        for (target, direction), xs in data.items()
        for j, x in enumerate(xs, start=1)
    ]
    return pd.DataFrame(rows)


# 2 targets x 2 directions x 3 cycles
BASE = {
    (0.0, +1): [1.0, 2.0, 3.0],
    (0.0, -1): [-1.0, 0.0, 1.0],
    (100.0, +1): [4.0, 6.0, 8.0],
    (100.0, -1): [5.0, 5.0, 5.0],
}
# Hand computation, per target (n = 3, ddof = 1 so divide the sum of squares by 2):
#   P=0   up  : mean (1+2+3)/3 = 2;  residuals -1,0,1 -> (1+0+1)/2 = 1 -> s = 1;  R_up = 4*1 = 4
#   P=0   down: mean (-1+0+1)/3 = 0; residuals -1,0,1 -> s = 1;                   R_down = 4
#   P=0   B = 2 - 0 = 2;  mean_bidir = (2+0)/2 = 1;  R = max(2*1 + 2*1 + |2| = 6, 4, 4) = 6
#   P=100 up  : mean (4+6+8)/3 = 6;  residuals -2,0,2 -> (4+0+4)/2 = 4 -> s = 2;  R_up = 8
#   P=100 down: mean 5;              residuals 0 -> s = 0;                        R_down = 0
#   P=100 B = 6 - 5 = 1;  mean_bidir = (6+5)/2 = 5.5;  R = max(2*2 + 2*0 + |1| = 5, 8, 0) = 8
# Axis:
#   B = max(|2|, |1|) = 2 (signed +2 at P=0);  B_mean = (2+1)/2 = 1.5
#   R_up = max(4, 8) = 8;  R_down = max(4, 0) = 4;  R = max(6, 8) = 8
#   E_up = 6 - 2 = 4;  E_down = 5 - 0 = 5;  E = max(2,6,0,5) - min(2,6,0,5) = 6 - 0 = 6
#   M = 5.5 - 1 = 4.5
#   A_up:   mean+2s = 2+2 = 4, 6+4 = 10 -> 10;   mean-2s = 2-2 = 0, 6-4 = 2 -> 0;   A_up = 10
#   A_down: mean+2s = 0+2 = 2, 5+0 = 5  -> 5;    mean-2s = 0-2 = -2, 5-0 = 5 -> -2; A_down = 7
#   A:      max(4, 10, 2, 5) = 10;  min(0, 2, -2, 5) = -2;  A = 12
BASE_AXIS = {
    "A_up_um": 10.0, "A_down_um": 7.0, "A_um": 12.0,
    "E_up_um": 4.0, "E_down_um": 5.0, "E_um": 6.0, "M_um": 4.5,
    "R_up_um": 8.0, "R_down_um": 4.0, "R_um": 8.0,
    "B_um": 2.0, "B_signed_um": 2.0, "B_target_mm": 0.0, "B_mean_um": 1.5,
    "n_cycles": 3.0, "n_targets": 2.0,
}


def _assert_axis(axis: dict, expected: dict) -> None:
    for key, want in expected.items():
        got = axis[key]
        if math.isnan(want):
            assert math.isnan(got), f"{key}: expected NaN, got {got}"
        else:
            assert got == pytest.approx(want, abs=1e-12), f"{key}: expected {want}, got {got}"


# ---------------------------------------------------------------- ISO 230-2 by hand ---
def test_two_targets_two_directions_three_cycles_by_hand():
    res = positioning_statistics(_table(BASE))
    per = res["per_target"]
    assert list(per.columns) == [
        "target_mm", "n_up", "n_down", "mean_up_um", "mean_down_um", "s_up_um", "s_down_um",
        "R_up_um", "R_down_um", "B_um", "mean_bidir_um", "R_bidir_um",
    ]
    assert per["target_mm"].tolist() == [0.0, 100.0]
    assert per["n_up"].tolist() == [3, 3] and per["n_down"].tolist() == [3, 3]
    np.testing.assert_allclose(per["mean_up_um"], [2.0, 6.0])
    np.testing.assert_allclose(per["mean_down_um"], [0.0, 5.0])
    np.testing.assert_allclose(per["s_up_um"], [1.0, 2.0])
    np.testing.assert_allclose(per["s_down_um"], [1.0, 0.0])
    np.testing.assert_allclose(per["R_up_um"], [4.0, 8.0])
    np.testing.assert_allclose(per["R_down_um"], [4.0, 0.0])
    np.testing.assert_allclose(per["B_um"], [2.0, 1.0])
    np.testing.assert_allclose(per["mean_bidir_um"], [1.0, 5.5])
    np.testing.assert_allclose(per["R_bidir_um"], [6.0, 8.0])
    _assert_axis(res["axis"], BASE_AXIS)
    assert set(res["axis"]) == set(BASE_AXIS)
    assert all(isinstance(v, float) for v in res["axis"].values())


def test_row_order_and_extra_columns_do_not_matter():
    df = _table(BASE, note="x").sample(frac=1.0, random_state=3).reset_index(drop=True)
    _assert_axis(positioning_statistics(df)["axis"], BASE_AXIS)


def test_coverage_factor_replaces_the_2():
    # k = 1:  R_i_up = 2*k*s:  P=0: 2*1 = 2, P=100: 2*2 = 4  -> R_up = 4
    #         R_i_down:        P=0: 2,      P=100: 0          -> R_down = 2
    #         R_i = max(k s_up + k s_down + |B|, R_up, R_down):
    #               P=0: max(1+1+2 = 4, 2, 2) = 4;  P=100: max(2+0+1 = 3, 4, 0) = 4  -> R = 4
    #         A_up: max(2+1, 6+2) = 8, min(2-1, 6-2) = 1 -> 7
    #         A:    max(3, 8, 0+1, 5+0) = 8, min(1, 4, 0-1, 5) = -1 -> 9
    axis = positioning_statistics(_table(BASE), coverage=1.0)["axis"]
    _assert_axis(axis, {"R_up_um": 4.0, "R_down_um": 2.0, "R_um": 4.0, "A_up_um": 7.0, "A_um": 9.0,
                        "E_um": 6.0, "B_um": 2.0, "M_um": 4.5})


def test_single_direction_run_has_no_reversal():
    up_only = {key: xs for key, xs in BASE.items() if key[1] == +1}
    res = positioning_statistics(_table(up_only))
    per = res["per_target"]
    assert per["n_down"].tolist() == [0, 0]
    assert per[["mean_down_um", "s_down_um", "R_down_um", "B_um", "mean_bidir_um", "R_bidir_um"]].isna().all().all()
    # the up figures are those of the bidirectional case; E and A reduce to E_up and A_up
    _assert_axis(res["axis"], {
        "A_up_um": 10.0, "A_down_um": NAN, "A_um": 10.0,
        "E_up_um": 4.0, "E_down_um": NAN, "E_um": 4.0, "M_um": NAN,
        "R_up_um": 8.0, "R_down_um": NAN, "R_um": NAN,
        "B_um": NAN, "B_signed_um": NAN, "B_target_mm": NAN, "B_mean_um": NAN,
        "n_cycles": 3.0, "n_targets": 2.0,
    })


def test_target_with_one_direction_is_excluded_from_bidirectional_figures():
    data = dict(BASE)
    data[(200.0, +1)] = [-3.0, -3.0, -3.0]  # mean -3, s 0, R_up 0; no down approach
    res = positioning_statistics(_table(data))
    row = res["per_target"].set_index("target_mm").loc[200.0]
    assert row["mean_up_um"] == -3.0 and row["s_up_um"] == 0.0 and row["n_down"] == 0
    assert math.isnan(row["B_um"]) and math.isnan(row["mean_bidir_um"]) and math.isnan(row["R_bidir_um"])
    # B, B_mean, M, R only over P=0 and P=100: unchanged (2, 1.5, 4.5, 8).
    # E_up = 6 - (-3) = 9;  E = max(2,6,-3,0,5) - min(...) = 6 - (-3) = 9
    # A_up = max(4, 10, -3+0) - min(0, 2, -3-0) = 10 - (-3) = 13;  A = max(.., 10) - min(.., -3) = 13
    _assert_axis(res["axis"], {
        "B_um": 2.0, "B_mean_um": 1.5, "M_um": 4.5, "R_um": 8.0, "R_up_um": 8.0, "R_down_um": 4.0,
        "E_up_um": 9.0, "E_down_um": 5.0, "E_um": 9.0, "A_up_um": 13.0, "A_down_um": 7.0, "A_um": 13.0,
        "n_targets": 3.0,
    })


def test_single_cycle_gives_nan_repeatability_and_accuracy_but_defined_means():
    # n = 1: s undefined -> R, A NaN (never computed with s = 0); E, B, M from the means alone.
    # P=0: up 1, down -1 -> B = 2, mean 0;  P=100: up 4, down 5 -> B = -1, mean 4.5
    # E = 5 - (-1) = 6;  E_up = 4 - 1 = 3;  E_down = 5 - (-1) = 6;  M = 4.5 - 0 = 4.5
    # B = max(|2|, |-1|) = 2 at P=0;  B_mean = (2 - 1)/2 = 0.5
    df = _table({(0.0, 1): [1.0], (0.0, -1): [-1.0], (100.0, 1): [4.0], (100.0, -1): [5.0]})
    res = positioning_statistics(df)
    assert res["per_target"]["s_up_um"].isna().all()
    _assert_axis(res["axis"], {
        "A_up_um": NAN, "A_down_um": NAN, "A_um": NAN, "R_up_um": NAN, "R_down_um": NAN, "R_um": NAN,
        "E_up_um": 3.0, "E_down_um": 6.0, "E_um": 6.0, "M_um": 4.5,
        "B_um": 2.0, "B_signed_um": 2.0, "B_target_mm": 0.0, "B_mean_um": 0.5, "n_cycles": 1.0,
    })


def test_negative_reversal_reports_its_sign_and_target():
    # P=0: up 0,0 down 1,1 -> B = -1;  P=50: up 0,0 down 3,3 -> B = -3  => B = 3, signed -3 at 50
    df = _table({(0.0, 1): [0.0, 0.0], (0.0, -1): [1.0, 1.0], (50.0, 1): [0.0, 0.0], (50.0, -1): [3.0, 3.0]})
    _assert_axis(positioning_statistics(df)["axis"],
                 {"B_um": 3.0, "B_signed_um": -3.0, "B_target_mm": 50.0, "B_mean_um": -2.0})


def test_positioning_statistics_by_group():
    # block "warm": every deviation doubled -> means and s double -> every range figure doubles:
    # A_up 20, A_down 14, A 24, E 12, M 9, R 16, B 4 (signed +4 at P=0), B_mean 3
    cold = _table(BASE, block="cold")
    warm = _table({k: [2 * x for x in xs] for k, xs in BASE.items()}, block="warm")
    out = positioning_statistics_by(pd.concat([warm, cold], ignore_index=True), "block")
    assert out["block"].tolist() == ["cold", "warm"]
    assert list(out.columns[:2]) == ["block", "A_up_um"]
    _assert_axis(out.iloc[0].drop("block").to_dict(), BASE_AXIS)
    _assert_axis(out.iloc[1].drop("block").to_dict(), {
        "A_up_um": 20.0, "A_down_um": 14.0, "A_um": 24.0, "E_up_um": 8.0, "E_down_um": 10.0, "E_um": 12.0,
        "M_um": 9.0, "R_up_um": 16.0, "R_down_um": 8.0, "R_um": 16.0,
        "B_um": 4.0, "B_signed_um": 4.0, "B_target_mm": 0.0, "B_mean_um": 3.0, "n_cycles": 3.0,
    })


def test_positioning_statistics_by_names_the_group_of_an_error():
    df = pd.concat([_table(BASE, block="a"), _table(BASE, block="b")], ignore_index=True)
    df.loc[len(df)] = {"target_mm": 0.0, "direction": 1, "cycle": 1, "deviation_um": 9.0, "block": "b"}
    with pytest.raises(ValueError, match=re.escape("block='b'") + ".*" + re.escape("(0.0, 1, 1)")):
        positioning_statistics_by(df, "block")
    with pytest.raises(ValueError, match="'hour'"):
        positioning_statistics_by(df, "hour")


# ------------------------------------------------------------- ISO 230-2 validation ---
@pytest.mark.parametrize(
    ("mutate", "pattern"),
    [
        (lambda df: df.drop(columns="cycle"), r"missing column.*'cycle'"),
        (lambda df: df.iloc[0:0], r"empty"),
        (lambda df: df.assign(deviation_um=df["deviation_um"].where(df.index != 2, np.nan)),
         r"'deviation_um' must be finite"),
        (lambda df: df.assign(target_mm=df["target_mm"].where(df.index != 0, np.inf)), r"'target_mm' must be finite"),
        (lambda df: df.assign(direction=df["direction"].replace(-1, 0)), r"'direction' must be \+1.*-1"),
        (lambda df: df.assign(cycle=df["cycle"] + 0.5), r"'cycle' must hold integers"),
        (lambda df: df.assign(deviation_um="a"), r"'deviation_um' must be numeric"),
        (lambda df: pd.concat([df, df.iloc[[4]]]),  # row 4 is (P=0, down, cycle 2)
         re.escape("duplicated (target_mm, direction, cycle) = (0.0, -1, 2)")),
        (lambda df: df.to_numpy(), r"expected a pandas DataFrame"),
    ],
)
def test_positioning_statistics_rejects_bad_readings(mutate, pattern):
    with pytest.raises(ValueError, match=pattern):
        positioning_statistics(mutate(_table(BASE)))


@pytest.mark.parametrize("coverage", [0.0, -2.0, np.nan, "two"])
def test_positioning_statistics_rejects_bad_coverage(coverage):
    with pytest.raises(ValueError, match="coverage"):
        positioning_statistics(_table(BASE), coverage=coverage)


# --------------------------------------------- property: independent re-implementation ---
def _reference(rows: list[tuple[float, int, int, float]], k: float) -> dict:
    """ISO 230-2 figures with plain loops (rows: target, direction, cycle, deviation)."""
    xs: dict[tuple[float, int], list[float]] = {}
    for target, direction, _cycle, x in rows:
        xs.setdefault((target, direction), []).append(x)
    targets = sorted({r[0] for r in rows})

    def mean(key):
        return statistics.fmean(xs[key]) if key in xs else None

    def sd(key):
        return statistics.stdev(xs[key]) if key in xs and len(xs[key]) >= 2 else NAN

    def max_or_nan(values):
        if not values or any(math.isnan(v) for v in values):
            return NAN
        return max(values)

    def min_or_nan(values):
        if not values or any(math.isnan(v) for v in values):
            return NAN
        return min(values)

    out = {}
    hi = {1: [], -1: []}
    lo = {1: [], -1: []}
    means = {1: [], -1: []}
    rep = {1: [], -1: []}
    b_values, bidir_means, r_bidir = [], [], []
    for t in targets:
        for d in (1, -1):
            if (t, d) in xs:
                m, s = mean((t, d)), sd((t, d))
                means[d].append(m)
                hi[d].append(m + k * s)
                lo[d].append(m - k * s)
                rep[d].append(2 * k * s)
        if (t, 1) in xs and (t, -1) in xs:
            b = mean((t, 1)) - mean((t, -1))
            b_values.append((t, b))
            bidir_means.append((mean((t, 1)) + mean((t, -1))) / 2)
            r_bidir.append(max(k * sd((t, 1)) + k * sd((t, -1)) + abs(b), 2 * k * sd((t, 1)), 2 * k * sd((t, -1)))
                           if not (math.isnan(sd((t, 1))) or math.isnan(sd((t, -1)))) else NAN)
    for d, tag in ((1, "up"), (-1, "down")):
        out[f"A_{tag}_um"] = max_or_nan(hi[d]) - min_or_nan(lo[d])
        out[f"E_{tag}_um"] = max(means[d]) - min(means[d]) if means[d] else NAN
        out[f"R_{tag}_um"] = max_or_nan(rep[d])
    out["A_um"] = max_or_nan(hi[1] + hi[-1]) - min_or_nan(lo[1] + lo[-1])
    out["E_um"] = max(means[1] + means[-1]) - min(means[1] + means[-1])
    out["M_um"] = max(bidir_means) - min(bidir_means) if bidir_means else NAN
    out["R_um"] = max_or_nan(r_bidir)
    if b_values:
        best_t, best_b = b_values[0]
        for t, b in b_values:
            if abs(b) > abs(best_b):
                best_t, best_b = t, b
        out.update(B_um=abs(best_b), B_signed_um=best_b, B_target_mm=best_t,
                   B_mean_um=sum(b for _, b in b_values) / len(b_values))
    else:
        out.update(B_um=NAN, B_signed_um=NAN, B_target_mm=NAN, B_mean_um=NAN)
    out["n_cycles"] = float(len({r[2] for r in rows}))
    out["n_targets"] = float(len(targets))
    return out


def test_matches_plain_loop_reimplementation_on_random_data():
    rng = np.random.default_rng(20240521)
    for trial in range(40):
        n_targets = int(rng.integers(1, 7))
        n_cycles = int(rng.integers(1, 6))
        targets = np.sort(rng.choice(np.arange(0, 1001, 25), size=n_targets, replace=False)).astype(float)
        rows = []
        for t in targets:
            # mostly bidirectional; sometimes one direction only (then the other is absent)
            dirs = [1, -1] if rng.random() < 0.75 else [int(rng.choice([1, -1]))]
            for d in dirs:
                # every now and then a cycle is missing at this target/direction
                cycles = [j for j in range(1, n_cycles + 1) if rng.random() < 0.9] or [1]
                for j in cycles:
                    rows.append((float(t), d, j, float(rng.normal(3.0 * d + 0.01 * t, 2.0))))
        k = float(rng.choice([1.0, 2.0, 3.0]))
        df = pd.DataFrame(rows, columns=["target_mm", "direction", "cycle", "deviation_um"])
        got = positioning_statistics(df.sample(frac=1.0, random_state=trial), coverage=k)["axis"]
        want = _reference(rows, k)
        assert set(got) == set(want)
        for key in want:
            if math.isnan(want[key]):
                assert math.isnan(got[key]), (trial, key, got[key])
            else:
                assert got[key] == pytest.approx(want[key], rel=1e-9, abs=1e-9), (trial, key)


# ------------------------------------------------------------------ ISO 230-3: drift ---
# t = 0..100 s every 10 s; x rises 2 µm per step to 10 at t = 50, then falls 3 µm per step to -5
T = np.arange(0.0, 101.0, 10.0)
X = np.array([0, 2, 4, 6, 8, 10, 7, 4, 1, -2, -5], dtype=float)


def test_drift_summary_whole_run_and_blocks_by_hand():
    out = drift_summary(T, X, blocks=[("heat", 0, 50), ("cool", 50, 100)]).set_index("block")
    assert out.index.tolist() == ["heat", "cool", "all"]
    # all: x0 = 0; |x| peaks at 10 (t = 50; |-5| is smaller); range 10 - (-5) = 15; final -5
    a = out.loc["all"]
    assert (a["start_s"], a["end_s"], a["n_samples"]) == (0.0, 100.0, 11)
    assert (a["max_drift_um"], a["max_drift_signed_um"], a["t_max_drift_s"]) == (10.0, 10.0, 50.0)
    assert (a["range_um"], a["final_drift_um"]) == (15.0, -5.0)
    assert (a["max_drift_from_start_um"], a["final_drift_from_start_um"]) == (10.0, -5.0)
    # heat (t 0..50, 6 samples 0,2,..,10): block start = run start = 0 -> max 10 at t 50, range 10, final 10
    h = out.loc["heat"]
    assert h["n_samples"] == 6
    assert (h["max_drift_um"], h["max_drift_signed_um"], h["t_max_drift_s"], h["range_um"], h["final_drift_um"]) == (
        10.0, 10.0, 50.0, 10.0, 10.0)
    assert (h["max_drift_from_start_um"], h["final_drift_from_start_um"]) == (10.0, 10.0)
    # cool (t 50..100, x 10,7,4,1,-2,-5): vs its first sample 10: 0,-3,-6,-9,-12,-15
    #   -> max 15, signed -15 at t 100, range 15, final -15
    # vs run start 0: 10,7,4,1,-2,-5 -> max 10, signed +10 at t 50, final -5
    c = out.loc["cool"]
    assert c["n_samples"] == 6
    assert (c["max_drift_um"], c["max_drift_signed_um"], c["t_max_drift_s"]) == (15.0, -15.0, 100.0)
    assert (c["range_um"], c["final_drift_um"]) == (15.0, -15.0)
    assert (c["max_drift_from_start_um"], c["max_drift_from_start_signed_um"],
            c["t_max_drift_from_start_s"], c["final_drift_from_start_um"]) == (10.0, 10.0, 50.0, -5.0)


def test_drift_summary_relative_to_first_value_not_zero():
    # x = 5, 3, 8: drifts -2, +3 -> max 3 (signed +3 at t 2); range 8 - 3 = 5; final +3
    out = drift_summary([0, 1, 2], [5, 3, 8])
    assert out["block"].tolist() == ["all"]
    r = out.iloc[0]
    assert (r["max_drift_um"], r["max_drift_signed_um"], r["t_max_drift_s"], r["range_um"], r["final_drift_um"]) == (
        3.0, 3.0, 2.0, 5.0, 3.0)


@pytest.mark.parametrize(
    ("args", "pattern"),
    [
        (([0, 1, 2], [1, 2]), r"mismatched lengths: t_s has 3, value_um has 2"),
        (([], []), r"t_s: empty"),
        (([0, 1, 2], [1, np.nan, 2]), r"value_um: must be finite"),
        (([0, 2, 1], [1, 2, 3]), r"t_s: must be strictly increasing"),
        (([0, 1, 2], [1, 2, 3], [("a", 5, 9)]), r"blocks\[0\] \('a'\): no sample"),
        (([0, 1, 2], [1, 2, 3], [("a", 2, 1)]), r"end_s=1.0 is before start_s=2.0"),
        (([0, 1, 2], [1, 2, 3], [("all", 0, 1)]), r"'all' is reserved"),
        (([0, 1, 2], [1, 2, 3], [("a", 0, 1), ("a", 1, 2)]), r"duplicated block name 'a'"),
        (([0, 1, 2], [1, 2, 3], [("a", 0)]), r"blocks\[0\]: expected \(name, start_s, end_s\)"),
    ],
)
def test_drift_summary_rejects_bad_input(args, pattern):
    with pytest.raises(ValueError, match=pattern):
        drift_summary(*args)


# ------------------------------------------------------------------- ISO 230-3: tilt ---
def test_tilt_by_hand():
    # b - a = 0, 4, -4 µm over 200 mm -> 0, 0.02, -0.02 µm/mm -> x1000 -> 0, 20, -20 µm/m (µrad)
    np.testing.assert_allclose(tilt([0.0, 2.0, 5.0], [0.0, 6.0, 1.0], 200.0), [0.0, 20.0, -20.0])
    # scalar: (3 - 1) µm / 100 mm = 0.02 µm/mm = 20 µrad
    assert float(tilt(1.0, 3.0, 100.0)) == pytest.approx(20.0)


@pytest.mark.parametrize(
    ("args", "pattern"),
    [
        (([0, 1], [0, 1], 0.0), r"spacing_mm: .*> 0"),
        (([0, 1], [0, 1], -5.0), r"spacing_mm"),
        (([0, 1], [0, 1], np.inf), r"spacing_mm: expected a finite number"),
        (([0, 1], [0, 1, 2], 100.0), r"mismatched shapes"),
        (([0, np.nan], [0, 1], 100.0), r"a_um: must be finite"),
        (([], [], 100.0), r"a_um: empty"),
    ],
)
def test_tilt_rejects_bad_input(args, pattern):
    with pytest.raises(ValueError, match=pattern):
        tilt(*args)


# ------------------------------------------------------------- ISO 230-3: error line ---
def test_error_line_recovers_exact_line():
    # deviation = 3 µm + 0.01 µm/mm * P  -> offset 3 µm, slope 0.01 µm/mm = 10 µm/m
    targets = [0.0, 100.0, 200.0, 300.0]
    offset, slope = error_line(targets, [3.0, 4.0, 5.0, 6.0])
    assert offset == pytest.approx(3.0) and slope == pytest.approx(10.0)


def test_error_line_least_squares_by_hand():
    # P = 0, 100, 200 and d = 0, 3, 0: mean P 100, mean d 1
    # slope = sum((P-100)(d-1)) / sum((P-100)^2) = ((-100)(-1) + 0*2 + (100)(-1)) / 20000 = 0
    # offset = 1 - 0 * 100 = 1
    offset, slope = error_line([0.0, 100.0, 200.0], [0.0, 3.0, 0.0])
    assert offset == pytest.approx(1.0) and slope == pytest.approx(0.0, abs=1e-12)
    # P = 100, 200 and d = 2, 0: slope -2 µm / 100 mm = -20 µm/m; at P = 0: 2 + 2 = 4
    offset, slope = error_line([100.0, 200.0], [2.0, 0.0])
    assert offset == pytest.approx(4.0) and slope == pytest.approx(-20.0)


def test_error_lines_per_cycle_and_change():
    # cycle 1 at t 0,10,20,30: d = 3 + 0.01 P      -> offset 3, slope 10 µm/m, mean t 15
    # cycle 2 at t 600..630:  d = 5 + 0.02 P      -> offset 5, slope 20 µm/m, mean t 615
    # change vs cycle 1: offset +2 µm, slope +10 µm/m
    p = [0.0, 100.0, 200.0, 300.0]
    df = pd.DataFrame({
        "cycle": [2] * 4 + [1] * 4,
        "target_mm": p + p,
        "t_s": [600.0, 610.0, 620.0, 630.0, 0.0, 10.0, 20.0, 30.0],
        "deviation_um": [5.0, 7.0, 9.0, 11.0, 3.0, 4.0, 5.0, 6.0],
    })
    out = error_lines(df)
    assert out["cycle"].tolist() == [1, 2]
    np.testing.assert_allclose(out["t_s"], [15.0, 615.0])
    assert out["n_points"].tolist() == [4, 4]
    np.testing.assert_allclose(out["offset_um"], [3.0, 5.0])
    np.testing.assert_allclose(out["slope_um_per_m"], [10.0, 20.0])
    np.testing.assert_allclose(out["offset_change_um"], [0.0, 2.0], atol=1e-12)
    np.testing.assert_allclose(out["slope_change_um_per_m"], [0.0, 10.0], atol=1e-12)


def test_error_line_rejects_bad_input():
    with pytest.raises(ValueError, match="at least two distinct targets"):
        error_line([100.0, 100.0], [1.0, 2.0])
    with pytest.raises(ValueError, match="mismatched lengths"):
        error_line([0.0, 100.0], [1.0])
    with pytest.raises(ValueError, match="deviation_um: must be finite"):
        error_line([0.0, 100.0], [1.0, np.inf])
    with pytest.raises(ValueError, match=r"missing column.*'t_s'"):
        error_lines(pd.DataFrame({"cycle": [1], "target_mm": [0.0], "deviation_um": [1.0]}))
    one_target = pd.DataFrame({"cycle": [1, 1, 2, 2], "target_mm": [0.0, 100.0, 50.0, 50.0],
                               "t_s": [0.0, 1.0, 2.0, 3.0], "deviation_um": [0.0, 1.0, 2.0, 3.0]})
    with pytest.raises(ValueError, match=r"cycle 2(\.0)?: .*at least two distinct targets"):
        error_lines(one_target)


# ------------------------------------------------------------------ ISO 230-3: ETVE ---
def test_environmental_variation_error_by_hand():
    # x = 1, 4, 2, -1, 0 -> range 4 - (-1) = 5 µm; ambient 20..22 -> range 2 °C; 5 / 2 = 2.5 µm/°C
    out = environmental_variation_error([0, 3600, 7200, 10800, 14400], [1, 4, 2, -1, 0], [20, 21, 22, 21.5, 20])
    assert out == {"etve_um": 5.0, "ambient_range_C": 2.0, "etve_um_per_C": 2.5,
                   "duration_s": 14400.0, "n_samples": 5.0}


def test_environmental_variation_error_constant_ambient_gives_nan_ratio():
    out = environmental_variation_error([0, 1], [0, 3], [20, 20])
    assert out["etve_um"] == 3.0 and out["ambient_range_C"] == 0.0 and math.isnan(out["etve_um_per_C"])


def test_environmental_variation_error_rejects_bad_input():
    with pytest.raises(ValueError, match="mismatched lengths.*ambient_C has 1"):
        environmental_variation_error([0, 1], [0, 3], [20])
    with pytest.raises(ValueError, match="ambient_C: must be finite"):
        environmental_variation_error([0, 1], [0, 3], [20, np.nan])
    with pytest.raises(ValueError, match="value_um: expected a 1-D"):
        environmental_variation_error([0, 1], [[0, 3]], [20, 21])
