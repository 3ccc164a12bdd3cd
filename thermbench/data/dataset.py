"""The validated dataset: metadata plus the process stream and the measured errors
(docs/dataset-format.md). Read with :func:`thermbench.data.io.load_dataset`, written with
:func:`thermbench.data.io.save_dataset`; one error channel in the shape the model families use
comes from :func:`thermbench.data.views.channel_view`."""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path

import pandas as pd
import yaml

from .schema import Metadata


class DatasetWarning(UserWarning):
    """A dataset loads, but something in it is ignored (a sensor column that ``metadata.yaml``
    does not declare); the message (one line) names the file and the column."""


@dataclass
class Dataset:
    """A validated dataset: metadata plus the process stream and the measured errors."""

    metadata: Metadata
    process: pd.DataFrame
    errors: pd.DataFrame
    path: Path | None = None
    channel: str | None = None  # a view of one error channel (thermbench.data.views.channel_view)

    @property
    def run_ids(self) -> list[str]:
        return list(self.metadata.runs)

    @property
    def sensor_columns(self) -> list[str]:
        return [self.metadata.sensor_column(s) for s in self.metadata.sensors]

    def process_run(self, run_id: str) -> pd.DataFrame:
        return self.process[self.process["run_id"] == run_id].reset_index(drop=True)

    def errors_run(self, run_id: str) -> pd.DataFrame:
        return self.errors[self.errors["run_id"] == run_id].reset_index(drop=True)

    def channel_view(self, channel: str) -> "Dataset":
        """One error channel in the shape the model families use (:func:`thermbench.data.views.channel_view`)."""
        from .views import channel_view  # views builds on this class: imported when first asked

        return channel_view(self, channel)

    def content_hash(self) -> str:
        """SHA-256 over the metadata and both tables (what tracking records)."""
        h = hashlib.sha256()
        h.update(yaml.safe_dump(self.metadata.model_dump(mode="json"), sort_keys=True).encode())
        for df in (self.process, self.errors):
            h.update(pd.util.hash_pandas_object(df, index=False).values.tobytes())
            h.update(",".join(df.columns).encode())
        return h.hexdigest()[:16]
