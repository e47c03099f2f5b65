"""Shared by the bench scripts: picture sheets of crops, a label above each tile."""

from __future__ import annotations

import numpy as np
import torch

LABEL_H = 14  # pixels of the label strip above each tile


def label_sheet(rows: list[list[tuple[str, torch.Tensor]]], zoom: int, min_width: int = 0):
    """A PIL image: one row per list of ``(label, tile [h,w,3] in [0,1])``, each tile enlarged ``zoom`` times
    (nearest) in a cell as large as the largest tile (at least ``min_width`` wide), its label above it."""
    from PIL import Image, ImageDraw

    tiles = [t for row in rows for _, t in row]
    th = max(t.shape[0] for t in tiles) * zoom + LABEL_H
    tw = max(max(t.shape[1] for t in tiles) * zoom, min_width)
    sheet = Image.new("RGB", (tw * max(len(row) for row in rows), th * len(rows)), "white")
    draw = ImageDraw.Draw(sheet)
    for r, row in enumerate(rows):
        for c, (label, t) in enumerate(row):
            a = (t.detach().float().cpu().numpy() * 255 + 0.5).astype(np.uint8).repeat(zoom, 0).repeat(zoom, 1)
            sheet.paste(Image.fromarray(a), (c * tw, r * th + LABEL_H))
            draw.text((c * tw + 2, r * th + 1), label, fill="black")
    return sheet
