"""Type aliases shared by public signatures."""
from __future__ import annotations

from typing import Any, Sequence, Union

import numpy as np
import torch

__all__ = ["ArrayLike", "Device"]

ArrayLike = Union[torch.Tensor, np.ndarray, Sequence[Any]]  # anything np.asarray / torch.as_tensor accepts
Device = Union[torch.device, str]
