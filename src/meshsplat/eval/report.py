"""Evaluation report: sample sheets (ground truth | render | error), training curves, one HTML page.

matplotlib (Agg backend) is imported only here, when a report is written.
"""

from __future__ import annotations

import base64
import csv
import html
from pathlib import Path

import numpy as np

__all__ = ["write_report", "read_log", "plot_samples", "plot_curves", "loss_curves", "LOSS_TERM_LABELS", "ERROR_VMAX"]

ERROR_VMAX = 0.25  # heat-map scale: mean absolute RGB error 0 .. ERROR_VMAX


def _plt():
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    return plt


def read_log(path: str | Path) -> dict[str, np.ndarray]:
    """Numeric columns of ``RUN/log.csv`` (rows that do not parse are skipped; an empty cell, a term not
    computed on that iteration, is nan; columns with no value are left out); empty when missing."""
    path = Path(path)
    if not path.is_file():
        return {}
    rows: list[dict[str, float]] = []
    with open(path, newline="") as fh:
        for row in csv.DictReader(fh):
            try:
                vals = {k: float(v) for k, v in row.items() if k and v not in (None, "")}
            except ValueError:
                continue
            if "iteration" in vals:
                rows.append(vals)
    keys = list(dict.fromkeys(k for r in rows for k in r))
    return {k: np.asarray([r.get(k, np.nan) for r in rows]) for k in keys}


def plot_samples(samples: list, path: str | Path, title: str = "") -> Path:
    """Rows of ``(label, gt [H,W,3], render [H,W,3], record)``: ground truth | render | error heat-map."""
    plt = _plt()
    rows = len(samples)
    h, w = samples[0][1].shape[:2]
    cell = 2.6
    fig_w, fig_h = 3 * cell * max(w / h, 0.5) + 0.9, rows * cell + 0.5
    fig, axes = plt.subplots(
        rows, 3, figsize=(fig_w, fig_h), squeeze=False, gridspec_kw={"wspace": 0.04, "hspace": 0.28}
    )
    dpi = max(80, min(200, int(min(w, 512) / cell)))
    im = None
    for r, (label, gt, img, rec) in enumerate(samples):
        gt_np, img_np = gt.numpy(), img.numpy()
        err = np.abs(img_np - gt_np).mean(-1)
        metrics = f"PSNR {rec['psnr']:.2f} dB" if rec.get("psnr") is not None else "PSNR inf"
        metrics += f", SSIM {rec['ssim']:.3f}"
        if rec.get("lpips") is not None:
            metrics += f", LPIPS {rec['lpips']:.3f}"
        panels = [(gt_np, "ground truth"), (img_np, "render"), (err, "|render - gt|")]
        for c, (data, name) in enumerate(panels):
            ax = axes[r, c]
            if c < 2:
                ax.imshow(np.clip(data, 0, 1), interpolation="nearest")
            else:
                im = ax.imshow(data, cmap="inferno", vmin=0.0, vmax=ERROR_VMAX, interpolation="nearest")
            ax.set_xticks([])
            ax.set_yticks([])
            ax.set_title(name if r == 0 else "", fontsize=9)
        axes[r, 0].set_ylabel(label, fontsize=7)
        axes[r, 1].set_xlabel(metrics, fontsize=7)
    cb = fig.colorbar(im, ax=axes[:, 2].tolist(), fraction=0.05, pad=0.02)
    cb.ax.tick_params(labelsize=7)
    cb.set_label("mean abs. RGB error", fontsize=7)
    if title:
        fig.suptitle(title, fontsize=10)
    path = Path(path)
    fig.savefig(path, dpi=dpi, bbox_inches="tight")
    plt.close(fig)
    return path


# log.csv's loss terms as the curves name them (unweighted values; "loss" is the weighted sum minimised)
LOSS_TERM_LABELS = {
    "l1": "L1",
    "mse": "MSE",
    "lpips": "LPIPS",
    "dssim": "D-SSIM",
    "scale": "scale (rel. to mesh)",
    "mask": "mask L1",
    "albedo": "albedo prior",
}


def _smooth(ax, it: np.ndarray, y: np.ndarray, color: str, label: str | None) -> None:
    """The raw curve faint, a moving average over ~5% of the rows on top (nan rows left out)."""
    ok = np.isfinite(y)
    it, y = it[ok], y[ok]
    if len(y) == 0:
        return
    ax.plot(it, y, lw=0.8, color=color, alpha=0.35 if len(y) > 20 else 1.0, label=None if len(y) > 20 else label)
    if len(y) > 20:
        k = max(2, len(y) // 20)
        ax.plot(it[k - 1 :], np.convolve(y, np.ones(k) / k, mode="valid"), lw=1.5, color=color, label=label)


def loss_curves(log: dict[str, np.ndarray]) -> list[tuple[str, str]]:
    """The loss panel's curves ``[(column, label)]``: the total, then each term the run computed (not
    all zero or empty); empty when the log has no loss column."""
    if "loss" not in log:
        return []
    terms = [(k, label) for k, label in LOSS_TERM_LABELS.items() if k in log and bool(np.nan_to_num(log[k]).any())]
    return [("loss", "total"), *terms]


def plot_curves(log: dict[str, np.ndarray], path: str | Path) -> Path | None:
    """The training loss and each of its terms (labelled; a term such as the scale regulariser, zero until
    Gaussians grow past its threshold, shows as its own curve), training PSNR and #Gaussians vs iteration;
    None when the log holds no rows."""
    if not log or len(log.get("iteration", [])) == 0:
        return None
    plt = _plt()
    it = log["iteration"]
    terms = [col for col, _ in loss_curves(log)[1:]]
    panels = [("loss", "loss (total) and its terms, unweighted", True)] if "loss" in log else []
    panels += [p for p in (("psnr", "train PSNR (dB)", False), ("n_gaussians", "#Gaussians", False)) if p[0] in log]
    fig, axes = plt.subplots(1, len(panels), figsize=(4.2 * len(panels) + (1.0 if terms else 0.0), 3.2), squeeze=False)
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for ax, (key, label, logy) in zip(axes[0], panels, strict=True):
        curves: list[tuple[str, str | None]] = [*loss_curves(log)] if key == "loss" else [(key, None)]
        for i, (col, name) in enumerate(curves):
            _smooth(ax, it, log[col], colors[i % len(colors)], name)
        values = np.concatenate([log[c][np.isfinite(log[c])] for c, _ in curves])
        if logy and bool((values > 0).any()):
            ax.set_yscale("log", nonpositive="mask")  # a term at zero (not yet active) leaves a gap
        if key == "loss" and terms:
            ax.legend(fontsize=7, loc="best")
        ax.set_xlabel("iteration")
        ax.set_title(label, fontsize=10)
        ax.grid(alpha=0.3)
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _img_tag(path: Path) -> str:
    data = base64.b64encode(path.read_bytes()).decode("ascii")
    return f'<img alt="{html.escape(path.name)}" src="data:image/png;base64,{data}">'


def _fmt(x, digits: int = 3) -> str:
    return "-" if x is None else f"{x:.{digits}f}"


def write_report(out_dir: str | Path, metrics: dict, samples: dict, log_csv: str | Path) -> dict[str, str]:
    """Write sample sheets, curves and ``report.html`` (images embedded) into ``out_dir``."""
    out = Path(out_dir)
    files: dict[str, str] = {}
    sheets = {}
    for name, rows in samples.items():
        if rows:
            sheets[name] = plot_samples(
                rows,
                out / f"samples_{name}.png",
                f"{name}: ground truth | render | error (iteration {metrics.get('iteration')})",
            )
            files[f"samples_{name}"] = str(sheets[name])
    curves = plot_curves(read_log(log_csv), out / "curves.png")
    if curves is not None:
        files["curves"] = str(curves)
    e = html.escape
    rows = "".join(
        f"<tr><td>{e(n)}</td><td>{s['n_frames']}</td><td>{_fmt(s['psnr'], 2)}</td><td>{_fmt(s['ssim'])}</td>"
        f"<td>{_fmt(s['lpips'])}</td><td>{_fmt(s.get('psnr_mask'), 2)}</td><td>{_fmt(s.get('ssim_mask'))}</td>"
        f"<td>{_fmt(s.get('lpips_mask'))}</td><td>{_fmt(s.get('psnr_crop'), 2)}</td><td>{_fmt(s.get('ssim_crop'))}</td>"
        f"<td>{_fmt(s.get('lpips_crop'))}</td><td>{_fmt(s['render_ms'], 1)}</td></tr>"
        for n, s in metrics["splits"].items()
    )
    parts = [
        "<!doctype html><html><head><meta charset='utf-8'><title>meshsplat evaluation</title><style>",
        "body{font-family:sans-serif;margin:2em;max-width:1200px}table{border-collapse:collapse;margin:1em 0}",
        "td,th{border:1px solid #ccc;padding:3px 8px;text-align:right}td:first-child{text-align:left}",
        "img{max-width:100%;image-rendering:pixelated}code{background:#f3f3f3}</style></head><body>",
        f"<h1>Evaluation of {e(str(metrics.get('run')))}</h1>",
        f"<p>checkpoint <code>{e(str(metrics.get('checkpoint')))}</code> (iteration {metrics.get('iteration')}), "
        f"{metrics.get('n_gaussians')} Gaussians, dataset <code>{e(str(metrics.get('dataset')))}</code>, "
        f"device {e(str(metrics.get('device')))}.</p>",
        (f"<p>Asset credit: {e(str(metrics['attribution']))}</p>" if metrics.get("attribution") else ""),
        f"<p>Renders and ground truth share one background, {e(str(metrics.get('background')))} "
        f"(ground truth composited through its mask). Full image: metrics over the whole frame; subject: "
        f"inside the ground-truth mask and on the crop around it (the honest figures when the subject is small). "
        f"LPIPS: {e(str(metrics.get('lpips_net') or metrics.get('lpips_note')))}.</p>",
        "<table><tr><th rowspan=2>split</th><th rowspan=2>frames</th><th colspan=3>full image</th>"
        "<th colspan=3>subject: in mask</th><th colspan=3>subject: crop</th><th rowspan=2>render ms/frame</th></tr>"
        "<tr><th>PSNR (dB)</th><th>SSIM</th><th>LPIPS</th><th>PSNR (dB)</th><th>SSIM</th><th>LPIPS</th>"
        f"<th>PSNR (dB)</th><th>SSIM</th><th>LPIPS</th></tr>{rows}</table>",
    ]
    if curves is not None:
        parts += ["<h2>Training curves</h2>", _img_tag(curves)]
    else:
        parts += ["<h2>Training curves</h2><p>no log.csv rows found.</p>"]
    for name, sheet in sheets.items():
        parts += [f"<h2>{e(name)}</h2>", _img_tag(sheet)]
    for name, s in metrics["splits"].items():
        body = "".join(
            f"<tr><td>{f['index']} {e(str(f['name']))}</td><td>{e(str(f['camera_id']))}</td>"
            f"<td>{_fmt(f['psnr'], 2)}</td><td>{_fmt(f['ssim'])}</td><td>{_fmt(f['lpips'])}</td>"
            f"<td>{_fmt(f['render_ms'], 1)}</td></tr>"
            for f in s["frames"]
        )
        parts.append(
            f"<details><summary>{e(name)}: per-frame metrics</summary><table><tr><th>frame</th>"
            f"<th>camera</th><th>PSNR</th><th>SSIM</th><th>LPIPS</th><th>ms</th></tr>{body}</table></details>"
        )
    parts.append("</body></html>")
    (out / "report.html").write_text("\n".join(parts), encoding="utf-8")
    files["report"] = str(out / "report.html")
    return files
