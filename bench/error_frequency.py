"""Where a trained model's held-out error lies in spatial frequency: speckle, texture detail or smooth shading.

    python bench/error_frequency.py --work runs/bench-quality_pbr --variants default default_lrdecay

Reads the captures and runs ``bench/quality_pbr.py`` left under ``--work`` (``data-<capture>-<renderer>``, its
``-spp<N>`` low-noise references, runs ``<capture>-<renderer>-<variant>``) and, per held-out split, on black,
in the mask's interior (the silhouette band, 2 px either side of the edge, left out so that blurring does not
carry edge error inside):

- ``psnr``: the interior PSNR of render vs reference;
- ``low<s>``: the PSNR of the error low-passed by a Gaussian of sigma ``s`` px (the same as blurring render
  and reference both; a normalised convolution over the interior only), ``high<s>``: of what is left
  (error minus its low-pass); ``lowshare<s>``: the low-pass part's share of the error power;
- ``hp_ref`` / ``hp_render``: the high-pass (sigma 1) power of the reference and of the render: a render
  with speckle has more than the reference, a blurry one less;
- ``gain4``: the interior PSNR after multiplying the render by the smooth (sigma 4) ratio reference / render
  of luminance: what correct smooth shading, at the model's own albedo, would score;
- ``bias``: the mean signed error (render - reference).

The same numbers for the capture itself against the references (``capture`` rows): the fingerprint of Monte
Carlo noise. Per frame: the interior RMS error (``--per-frame``). ``--picture``: reference | render |
|error| x4 | |low-passed error (sigma 4)| x4, cropped to the subject, one held-out frame and one held-out view
per variant (``--pick``: their position in the split). Saves bench/results/<name>-<host>.json.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from PIL import Image

from _machine import machine_info, results_path
from meshsplat.data import open_dataset
from meshsplat.metrics.budget import silhouette_regions
from meshsplat.metrics.ssim import gaussian_blur
from meshsplat.render.background import composite
from meshsplat.run_folder import load_avatar

SIGMAS = (1.0, 2.0, 4.0, 8.0)


def _lowpass(x: torch.Tensor, w: torch.Tensor, sigma: float) -> torch.Tensor:
    """Normalised convolution: the blur of ``x [H,W,C]`` over the pixels where ``w [H,W,1]`` is 1."""
    return gaussian_blur(x * w, sigma) / gaussian_blur(w, sigma).clamp_min(1e-6)


def _psnr(sq: torch.Tensor) -> float:
    return float(-10 * torch.log10(sq.clamp_min(1e-12)))


def analyse(img: torch.Tensor, gt: torch.Tensor, interior: torch.Tensor) -> dict[str, float]:
    """The frequency split of the error of ``img [H,W,3]`` vs ``gt [H,W,3]`` in ``interior [H,W]``."""
    w = interior[..., None].float()
    sel = interior
    err = img - gt
    out: dict[str, float] = {"psnr": _psnr(err[sel].pow(2).mean()), "bias": float(err[sel].mean())}
    total = float(err[sel].pow(2).mean())
    for s in SIGMAS:
        low = _lowpass(err, w, s)
        high = err - low
        out[f"low{s:g}"] = _psnr(low[sel].pow(2).mean())
        out[f"high{s:g}"] = _psnr(high[sel].pow(2).mean())
        out[f"lowshare{s:g}"] = float(low[sel].pow(2).mean()) / max(total, 1e-12)
    out["hp_ref"] = float((gt - _lowpass(gt, w, 1.0))[sel].pow(2).mean())
    out["hp_render"] = float((img - _lowpass(img, w, 1.0))[sel].pow(2).mean())
    lum_r, lum_g = img.mean(-1, keepdim=True), gt.mean(-1, keepdim=True)
    gain = _lowpass(lum_g, w, 4.0) / _lowpass(lum_r, w, 4.0).clamp_min(1e-3)
    out["gain4"] = _psnr((img * gain - gt)[sel].pow(2).mean())
    return out


def _crop_box(mask: torch.Tensor, pad: int = 6) -> tuple[int, int, int, int]:
    ys, xs = torch.nonzero(mask[..., 0] > 0.5, as_tuple=True)
    H, W = mask.shape[:2]
    return (
        max(0, int(ys.min()) - pad),
        min(H, int(ys.max()) + pad + 1),
        max(0, int(xs.min()) - pad),
        min(W, int(xs.max()) + pad + 1),
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--work", required=True)
    ap.add_argument("--capture", default="cesium")
    ap.add_argument("--renderer", default="pbr")
    ap.add_argument("--ref-spp", type=int, default=256, help="the references' folder suffix (0: the capture)")
    ap.add_argument("--variants", nargs="*", default=["default"])
    ap.add_argument("--name", default="error_frequency")
    ap.add_argument("--picture", default=None, help="PNG: crops of one held-out frame and view per variant")
    ap.add_argument("--pick", type=int, default=0, help="--picture: the frame at this position in each split")
    ap.add_argument("--per-frame", action="store_true")
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)

    work = Path(args.work)
    data = work / f"data-{args.capture}-{args.renderer}"
    ref = data.with_name(data.name + f"-spp{args.ref_spp}") if args.ref_spp else data
    if not ref.exists():
        ref = data
    ds, refs = open_dataset(data), open_dataset(ref)
    by_name = {refs.frame_info(j)["name"]: j for j in range(len(refs))}
    avatars = {v: load_avatar(work / f"{args.capture}-{args.renderer}-{v}") for v in args.variants}
    black = torch.zeros(3)
    rows: dict = {}
    tiles: dict = {}
    for split in [s for s in ds.split_names if s != "train"]:
        per: dict[str, list[dict[str, float]]] = {k: [] for k in ["capture", *args.variants]}
        for n, i in enumerate(ds.split(split)):
            fr, target = ds[i], refs[by_name[ds.frame_info(i)["name"]]]
            gt = composite(target.image, target.mask, black).float()
            interior = silhouette_regions(target.mask)["interior"]
            if ref != data:
                per["capture"].append(analyse(composite(fr.image, fr.mask, black).float(), gt, interior))
            for v, av in avatars.items():
                with torch.no_grad():
                    img = av.render(fr.vertices, fr.camera, black).image.float().clamp(0, 1)
                a = analyse(img, gt, interior)
                a["frame"] = ds.frame_info(i)["name"]
                per[v].append(a)
                if n == args.pick:
                    err = (img - gt).abs()
                    low = _lowpass(img - gt, interior[..., None].float(), 4.0).abs() * interior[..., None]
                    y0, y1, x0, x1 = _crop_box(target.mask)
                    row = [gt, img, (4 * err).clamp(0, 1), (4 * low).clamp(0, 1)]
                    tiles[(split, v)] = torch.cat([t[y0:y1, x0:x1] for t in row], 1)
        rows[split] = {}
        for k, lst in per.items():
            if not lst:
                continue
            keys = [q for q in lst[0] if q != "frame"]
            rows[split][k] = {q: sum(r[q] for r in lst) / len(lst) for q in keys}
            if k != "capture":
                rows[split][k]["rms_per_frame"] = [
                    (r["frame"], round(10 ** (-r["psnr"] / 20), 4)) for r in lst
                ]  # interior RMS error per frame

    hdr = f"{'split':<12}{'model':<22}{'PSNRint':>8}" + "".join(
        f"{'low' + f'{s:g}':>7}{'high' + f'{s:g}':>7}{'lo%':>5}" for s in SIGMAS
    )
    print(hdr + f"{'hp_ref':>8}{'hp_rend':>8}{'gain4':>7}{'bias':>8}")
    for split, r in rows.items():
        for k, m in r.items():
            line = f"{split:<12}{k:<22}{m['psnr']:>8.2f}"
            for s in SIGMAS:
                line += f"{m[f'low{s:g}']:>7.2f}{m[f'high{s:g}']:>7.2f}{100 * m[f'lowshare{s:g}']:>5.0f}"
            print(line + f"{m['hp_ref']:>8.4f}{m['hp_render']:>8.4f}{m['gain4']:>7.2f}{m['bias']:>8.4f}")
            if args.per_frame and "rms_per_frame" in m:
                print("    interior RMS per frame:", " ".join(f"{f}:{e:.3f}" for f, e in m["rms_per_frame"]))
    out = results_path(args.name)
    out.write_text(json.dumps({"machine": machine_info(), "args": vars(args), "splits": rows}, indent=2) + "\n")
    print(f"saved {out}")
    if args.picture and tiles:
        strips = list(tiles.values())
        w = max(t.shape[1] for t in strips)
        strips = [F.pad(t.permute(2, 0, 1), (0, w - t.shape[1])).permute(1, 2, 0) for t in strips]
        img = torch.cat(strips, 0).repeat_interleave(2, 0).repeat_interleave(2, 1)
        Path(args.picture).parent.mkdir(parents=True, exist_ok=True)
        Image.fromarray((img.numpy() * 255 + 0.5).astype(np.uint8)).save(args.picture)
        print(f"picture: {args.picture} (rows: {', '.join(f'{s}/{v}' for s, v in tiles)})")


if __name__ == "__main__":
    main()
