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


class ThermbenchPyfunc(mlflow.pyfunc.PythonModel):
    def load_context(self, context):
        from pathlib import Path

        from thermbench.data.errors import DatasetError
        from thermbench.data.files import read_capped
        from thermbench.data.limits import METADATA_MAX_BYTES
        from thermbench.data.safe_yaml import YAMLInputError, load_yaml

        self.model = joblib.load(context.artifacts["model"])
        path = Path(context.artifacts["metadata"])  # the training dataset's metadata.yaml, logged with the model
        try:
            self.metadata, _ = load_yaml(read_capped(path, METADATA_MAX_BYTES, "metadata.yaml").decode("utf-8-sig"))
        except UnicodeDecodeError:
            raise DatasetError(f"{path}: not UTF-8 text") from None
        except YAMLInputError as exc:
            raise DatasetError(f"{path}: {exc}") from None
        if not isinstance(self.metadata, dict):
            raise DatasetError(f"{path}: expected a mapping (the dataset's metadata), got {type(self.metadata).__name__}")

    def predict(self, context, model_input: pd.DataFrame, params=None) -> pd.DataFrame:
        from thermbench.data.dataset import Dataset
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
