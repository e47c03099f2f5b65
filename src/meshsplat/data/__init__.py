"""Native dataset format: validated lazy loader and writer (docs/dataset-format.md)."""

from meshsplat.data.dataset import AvatarDataset, Frame
from meshsplat.data.manifest import open_dataset
from meshsplat.data.writer import FORMAT_NAME, FORMAT_VERSION, DatasetWriter, write_dataset

__all__ = ["AvatarDataset", "Frame", "open_dataset", "DatasetWriter", "write_dataset", "FORMAT_NAME", "FORMAT_VERSION"]
