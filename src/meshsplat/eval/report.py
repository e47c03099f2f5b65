"""Evaluation report: sample sheets (ground truth | render | error), training curves, one HTML page.

matplotlib (Agg backend) is imported only here, when a report is written.
"""

from __future__ import annotations

import base64
import csv
import html
from pathlib import Path

import numpy as np

__all__ = ["write_report", "read_log", "plot_samples", "plot_curves", "ERROR_VMAX"]

ERROR_VMAX = 0.25  # heat-map scale: mean absolute RGB error 0 .. ERROR_VMAX


def _plt():
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    return plt


def read_log(path: str | Path) -> dict[str, np.ndarray]:
    """Numeric columns of ``RUN/log.csv`` (rows that do not parse are skipped); empty when missing."""
    path = Path(path)
    if not path.is_file():
        return {}
    cols: dict[str, list[float]] = {}
    with open(path, newline="") as fh:
        for row in csv.DictReader(fh):
            try:
                vals = {k: float(v) for k, v in row.items() if k and v not in (None, "")}
            except ValueError:
                continue
            if "iteration" not in vals:
                continue
            for k, v in vals.items():
                cols.setdefault(k, []).append(v)
    n = len(cols.get("iteration", []))
    return {k: np.asarray(v) for k, v in cols.items() if len(v) == n}


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


def plot_curves(log: dict[str, np.ndarray], path: str | Path) -> Path | None:
    """Loss, training PSNR and #Gaussians vs iteration; None when the log holds no rows."""
    if not log or len(log.get("iteration", [])) == 0:
        return None
    plt = _plt()
    it = log["iteration"]
    panels = [("loss", "loss", True), ("psnr", "train PSNR (dB)", False), ("n_gaussians", "#Gaussians", False)]
    panels = [p for p in panels if p[0] in log]
    fig, axes = plt.subplots(1, len(panels), figsize=(4.2 * len(panels), 3.2), squeeze=False)
    for ax, (key, label, logy) in zip(axes[0], panels, strict=True):
        y = log[key]
        ax.plot(it, y, lw=0.8, color="tab:blue", alpha=0.45 if len(y) > 20 else 1.0)
        if len(y) > 20:  # moving average over ~5% of the rows
            k = max(2, len(y) // 20)
            ax.plot(it[k - 1 :], np.convolve(y, np.ones(k) / k, mode="valid"), lw=1.5, color="tab:blue")
        if logy and bool((y > 0).all()):
            ax.set_yscale("log")
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
