"""Contact sheet: a grid of sample frames (image row over mask row) from a dataset."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from meshsplat.data import AvatarDataset, open_dataset
from meshsplat.io.images import float_to_uint8

__all__ = ["contact_sheet"]


def contact_sheet(
    dataset: AvatarDataset | Path | str,
    out_png: Path | str,
    indices: Sequence[int] | None = None,
    count: int = 8,
    tile: int = 128,
) -> Path:
    """Save a PNG grid: for each chosen frame its image (top) and mask (bottom), ``tile`` px each."""
    from PIL import Image

    ds = open_dataset(dataset, check_masks=False) if isinstance(dataset, (str, Path)) else dataset
    if indices is None:
        indices = np.linspace(0, len(ds) - 1, min(count, len(ds))).round().astype(int).tolist()
    cols = []
    for i in indices:
        fr = ds[int(i)]
        img = Image.fromarray(float_to_uint8(fr.image)).resize((tile, tile), Image.Resampling.BILINEAR)
        m = fr.mask if fr.mask is not None else fr.image.mean(-1, keepdim=True) * 0
        msk = Image.fromarray(float_to_uint8(m[..., 0])).convert("RGB").resize((tile, tile))
        col = Image.new("RGB", (tile, 2 * tile))
        col.paste(img, (0, 0))
        col.paste(msk, (0, tile))
        cols.append(col)
    sheet = Image.new("RGB", (tile * len(cols) + 2 * (len(cols) - 1), 2 * tile), (255, 255, 255))
    for k, c in enumerate(cols):
        sheet.paste(c, (k * (tile + 2), 0))
    out = Path(out_png)
    out.parent.mkdir(parents=True, exist_ok=True)
    sheet.save(out, optimize=True)
    return out
