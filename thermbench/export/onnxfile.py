"""The ONNX file of a neural model's thermal part (``model.onnx`` of an export directory), checked
with onnxruntime against the Python model."""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Sequence

import numpy as np


def write_onnx(model, path: Path, ds=None, runs: Sequence[str] = ()) -> dict:
    """The net's thermal part as ONNX (float32, inputs in raw units, standardisation inside),
    run by onnxruntime against the Python model; returns the check's figures."""
    import io

    from ..errors import require
    from ..models.neural import GRUModel, torch

    nn = torch.nn
    ort = require("onnxruntime", "the ONNX export of a neural model (or set export.onnx=false)")
    require("onnx", "the ONNX export of a neural model (or set export.onnx=false)")

    gru = isinstance(model, GRUModel)
    means = [torch.tensor(np.asarray(m, dtype=np.float32)) for m in model.input_mean_]
    scales = [torch.tensor(np.asarray(s, dtype=np.float32)) for s in model.input_scale_]
    net = _float32_copy(model.net_)
    ym, ys = float(model.y_mean_um_), float(model.y_scale_um_)

    class Wrap(nn.Module):
        def forward(self, *xs):
            z = [(x - m) / s for x, m, s in zip(xs, means, scales)]
            return net(*z) * ys + ym

    S = len(model.sensors_)
    if gru:
        example = (torch.zeros(2, model.n_lags_ + 1, S), torch.zeros(2, 1))
        names = ["dT_history_C", "axis_mm"]
        axes = {"dT_history_C": {0: "n"}, "axis_mm": {0: "n"}, "thermal_um": {0: "n"}}
    else:
        example = (torch.zeros(2, S + 1),)
        names = ["dT_C_and_axis_mm"]
        axes = {"dT_C_and_axis_mm": {0: "n"}, "thermal_um": {0: "n"}}
    buf = io.BytesIO()
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore")  # tracer notes on the GRU's shape checks; the result is checked below
        torch.onnx.export(Wrap().eval(), example, buf, dynamo=False, input_names=names, output_names=["thermal_um"],
                          dynamic_axes=axes, opset_version=17)  # fmt: skip
    data = buf.getvalue()
    path.write_bytes(data)
    # check: onnxruntime against the Python model on held-out readings (or the training scale)
    if ds is not None and runs:
        from ..models.base import readings

        rd = readings(ds, list(runs))
        feats = [model._inputs(ds, r, g["t_s"].to_numpy(), g["target_mm"].to_numpy()) for r, g in rd.groupby("run_id", sort=False)]
        inputs = [np.concatenate([f[i] for f in feats]) for i in range(len(feats[0]))]
        with torch.no_grad():
            ref = model._forward(inputs).numpy() * ys + ym
    else:
        rng = np.random.default_rng(0)
        inputs = [m + s * rng.standard_normal((64, *np.shape(m))) for m, s in zip(model.input_mean_, model.input_scale_)]
        if gru:
            inputs[0] = np.repeat(inputs[0][:, None, :], model.n_lags_ + 1, axis=1)
        with torch.no_grad():
            ref = model._forward(inputs).numpy() * ys + ym
    sess = ort.InferenceSession(data, providers=["CPUExecutionProvider"])
    got = sess.run(None, {n: np.asarray(a, dtype=np.float32) for n, a in zip(names, inputs)})[0]
    return {"file": path.name, "bytes": len(data), "inputs": names, "output": "thermal_um",
            "onnxruntime_max_abs_diff_um": float(np.max(np.abs(got - ref))), "n_checked": int(ref.size),
            "note": "thermal part only, float32; the geometric part is in the .tbm file"}  # fmt: skip


def _float32_copy(net):
    import copy

    out = copy.deepcopy(net).float().eval()
    for p in out.parameters():
        p.requires_grad_(False)
    return out
