"""``RUN/log.csv``: one row per ``log_every`` iterations (``LOG_COLUMNS``), kept up to the resumed iteration."""

from __future__ import annotations

import csv
import math
from pathlib import Path

__all__ = ["LOG_COLUMNS", "LOGGED_PARTS", "RunLog"]

LOGGED_PARTS = ("l1", "lpips", "scale", "mse", "dssim", "mask", "albedo")  # loss parts (components' by log_column)
LOG_COLUMNS = (
    "iteration",
    "loss",
    "l1",
    "lpips",
    "scale",
    "mse",
    "dssim",
    "psnr",
    "n_gaussians",
    "walked",
    "lr_duv",
    "lr_d",
    "time_s",
    "mask",  # component mask_loss, unweighted
    "albedo",  # component albedo_prior, unweighted
)


def _cell(value: float | int) -> str | float | int:
    """Floats to 6 significant digits; nan (a term not computed on that iteration, ``loss.lpips_every``) empty."""
    if isinstance(value, float):
        return "" if math.isnan(value) else f"{value:.6g}"
    return value


class RunLog:
    def __init__(self, path: Path) -> None:
        self.path = path

    def open(self, iteration: int) -> None:
        """Start the file anew, keeping the rows up to ``iteration`` (a resumed run's)."""
        rows = []
        if self.path.exists():
            with open(self.path, newline="") as fh:
                rows = [
                    r
                    for r in csv.DictReader(fh)
                    if r.get("iteration", "").isdigit() and int(r["iteration"]) <= iteration
                ]
        with open(self.path, "w", newline="") as fh:
            wr = csv.DictWriter(fh, fieldnames=LOG_COLUMNS)
            wr.writeheader()
            for r in rows:
                wr.writerow({k: r.get(k, "") for k in LOG_COLUMNS})

    def append(self, row: dict[str, float]) -> None:
        with open(self.path, "a", newline="") as fh:
            csv.DictWriter(fh, fieldnames=LOG_COLUMNS).writerow({k: _cell(row[k]) for k in LOG_COLUMNS})
