"""Type aliases shared by public signatures."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import torch

__all__ = ["ArrayLike", "Device"]

ArrayLike = torch.Tensor | np.ndarray | Sequence[Any]  # anything np.asarray / torch.as_tensor accepts
Device = torch.device | str
