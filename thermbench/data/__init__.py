"""The dataset contract: validated loading and atomic writing (docs/dataset-format.md)."""

from .io import Dataset, DatasetError, load_dataset, save_dataset
from .schema import FORMAT, KNOWN_LOCATIONS, Metadata

__all__ = ["Dataset", "DatasetError", "FORMAT", "KNOWN_LOCATIONS", "Metadata", "load_dataset", "save_dataset"]
