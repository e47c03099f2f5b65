"""Side-by-side crops around the subject: ground truth | each run's render, one row per held-out frame.

    python bench/subject_crops.py runs/bench-quality/paper runs/bench-quality/default --out crops.png

Renders the newest checkpoint of each run on a few frames of each test split (white background),
crops the mask's bounding box (padded) and scales it up by ``--zoom`` (nearest) so blotches and
silhouettes are visible. Row labels give the subject PSNR (inside the mask) of each render.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", nargs="+")
    ap.add_argument("--out", required=True)
    ap.add_argument("--per-split", type=int, default=2)
    ap.add_argument("--zoom", type=int, default=2)
    args = ap.parse_args()

    from _sheets import label_sheet
    from meshsplat.metrics import psnr
    from meshsplat.metrics.subject import subject_box
    from meshsplat.run_folder import load_run

    torch.set_num_threads(1)
    runs = [load_run(r, "cpu") for r in args.runs]
    ds = runs[0].open_dataset()
    rows = []
    for split in [s for s in ds.split_names if s != "train"]:
        ids = ds.split(split)
        pick = [ids[round(x)] for x in np.linspace(0, len(ids) - 1, min(args.per_split, len(ids)))]
        for i in pick:
            fr = ds[i]
            m = fr.mask
            gt = fr.image * m + (1 - m)
            y0, y1, x0, x1 = subject_box(m, pad=0.05)
            tiles, labels = [gt[y0:y1, x0:x1]], [f"{split} #{i} GT"]
            for run in runs:
                with torch.no_grad():
                    img = run.avatar.render(fr.vertices, fr.camera, background=torch.ones(3)).image.clamp(0, 1)
                tiles.append(img[y0:y1, x0:x1])
                labels.append(f"{Path(run.run_dir).name} {float(psnr(img, gt, mask=m)):.2f} dB")
            rows.append((tiles, labels))
    canvas = label_sheet([list(zip(labels, tiles, strict=True)) for tiles, labels in rows], args.zoom)
    canvas.save(args.out)
    print(f"saved {args.out}")


if __name__ == "__main__":
    main()
