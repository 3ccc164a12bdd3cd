"""The MLflow pyfunc face of a fitted thermbench model (logged as models-from-code).

``predict(process_log)`` takes a DataFrame with the dataset contract's process
columns (``t_s``, ``axis_mm``, ``feed_mm_min``, the sensor columns
``<sensor>_C`` the model needs, optionally ``run_id``) and returns the
predicted positioning error ``error_um`` at each row's (t_s, axis_mm): what a
compensator would subtract at that moment.
"""

from __future__ import annotations

import joblib
import mlflow
import numpy as np
import pandas as pd
import yaml


class ThermbenchPyfunc(mlflow.pyfunc.PythonModel):
    def load_context(self, context):
        self.model = joblib.load(context.artifacts["model"])
        with open(context.artifacts["metadata"], encoding="utf-8") as fh:
            self.metadata = yaml.safe_load(fh)

    def predict(self, context, model_input: pd.DataFrame, params=None) -> pd.DataFrame:
        from thermbench.data.io import Dataset
        from thermbench.data.schema import Metadata

        log = model_input.copy()
        if "run_id" not in log.columns:
            log.insert(0, "run_id", "live")
        log["run_id"] = log["run_id"].astype(str)
        runs = list(dict.fromkeys(log["run_id"]))
        meta = dict(self.metadata)
        meta["runs"] = {
            r: {"condition": {"stroke_mm": 0.0, "start_mm": 0.0, "end_mm": 0.0, "feed_mm_min": 0.0}} for r in runs
        }
        errors = pd.DataFrame({"run_id": pd.Series(dtype=str), "t_s": [], "target_mm": [], "error_um": []})
        ds = Dataset(Metadata.model_validate(meta), log.reset_index(drop=True), errors)
        out = np.empty(len(log))
        for r in runs:
            rows = np.flatnonzero(log["run_id"].to_numpy() == r)
            pr = log.iloc[rows]
            out[rows] = self.model.predict_at(ds, r, pr["t_s"].to_numpy(), pr["axis_mm"].to_numpy())
        return pd.DataFrame({"error_um": out}, index=model_input.index)


mlflow.models.set_model(ThermbenchPyfunc())
