"""thermbench.bench.metrics on hand-computed cases."""

import numpy as np
import pytest

from thermbench.bench.metrics import residual_metrics


def test_hand_computed_metrics():
    measured = np.array([0.0, 10.0, 20.0, -5.0])
    predicted = np.array([1.0, 8.0, 20.0, -5.0])  # residuals -1, 2, 0, 0
    m = residual_metrics(measured, predicted)
    assert m["rmse_um"] == pytest.approx(np.sqrt((1 + 4) / 4))
    assert m["max_abs_residual_um"] == 2.0
    assert m["pv_residual_um"] == 3.0
    assert m["max_abs_error_um"] == 20.0
    assert m["pv_error_um"] == 25.0
    assert m["compensation_rate"] == pytest.approx(1 - 2 / 20)  # seed 000 / 002 definition
    assert m["residual_fraction_of_pv"] == pytest.approx(2 / 25)  # seed 000's 15 % criterion


def test_rates_refer_to_the_thermal_error():
    """With a geometric part in the readings, the rates are judged against the thermal error."""
    geometric = np.array([3.0, -3.0, 3.0])
    thermal = np.array([0.0, 5.0, 10.0])
    measured = geometric + thermal
    predicted = measured - np.array([0.0, 0.5, -1.0])
    m = residual_metrics(measured, predicted, thermal)
    assert m["compensation_rate"] == pytest.approx(1 - 1.0 / 10.0)
    assert m["residual_fraction_of_pv"] == pytest.approx(1.0 / 10.0)


def test_perfect_and_useless_predictions():
    e = np.linspace(0, 40, 9)
    assert residual_metrics(e, e)["compensation_rate"] == 1.0
    assert residual_metrics(e, np.zeros_like(e))["compensation_rate"] == 0.0  # no compensation


def test_bad_input():
    with pytest.raises(ValueError, match="equal length"):
        residual_metrics([1.0, 2.0], [1.0])
    with pytest.raises(ValueError, match="no samples"):
        residual_metrics([], [])
    with pytest.raises(ValueError, match="non-finite"):
        residual_metrics([1.0, 2.0], [1.0, np.nan])
