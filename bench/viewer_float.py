"""Benchmark the player's float blending (the splats blended into an RGBA16F target, then one
full-screen pass clamps the image into the canvas) against the 8-bit path (``?float=0``: straight
into the canvas, as the page drew before), in the same run, headless Chromium (SwiftShader WebGL2).

Cost: the page's ``timeDraws(n, float)`` draws the current frame again, each draw followed by a
1-pixel readback that waits for the GPU, so a time covers the splat draw, the full-screen pass and
the readback's round trip; one draw through the float target, one through the 8-bit path,
alternating in the same page (15 rounds); medians and the median of the paired differences. Cases: random
shaded avatars (SH degree 1, learned irradiance) on CesiumMan's vertex frames, 20k Gaussians at 256²
and 800², 100k at 800². Under SwiftShader the GPU work runs on the CPU: the numbers say how much the
extra pass adds relative to the splats on this machine, not what a real GPU spends.

Accuracy: screenshots against ``avatar.render`` (PSNR on the full frame and on the subject, the pixels
either image draws), float and 8-bit: the 20k shaded avatar above (frame 20, 800²), and CesiumMan
live glTF with an aligned key light of intensity 1.6 on albedos 0.3-0.8 (6,000 Gaussians, 256²,
t = 0.8 s), where Gaussians exceed 1 and overlap with partial alpha.

Usage: python bench/viewer_float.py [--quick] [--out bench/results/viewer_float-<host>.json]
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch

from _machine import machine_info, results_path
from meshsplat.camera import Camera
from meshsplat.gaussians import Avatar, init_params
from meshsplat.gaussians.shading import KEY_STAGES, Shading
from meshsplat.mesh import TriMesh
from meshsplat.viewer import read_viewer_bundle, write_viewer_bundle
from viewer import cesium, live_rig, psnr, random_avatar

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))  # the headless-Chromium driver the browser tests use
from _browser import find_chromium, open_page  # noqa: E402

PATHS = {"float": "", "8-bit": "&float=0"}


def time_draws(index: Path, query: str, size: int, rounds: int) -> dict[str, list[float]]:
    """The page at ``query`` (paused): ``rounds`` x (one draw through the float target, one through the
    8-bit path), alternating in the same page, each waited for (ms)."""
    with open_page(index.as_uri() + f"?ui=0&play=0{query}", size, size) as page:
        page.wait_ready(300)
        assert page.evaluate("window.meshsplatViewer.floatTarget") is True
        page.evaluate("window.meshsplatViewer.timeDraws(1, true)")  # warm-up, both paths
        page.evaluate("window.meshsplatViewer.timeDraws(1, false)")
        out: dict[str, list[float]] = {"float": [], "8-bit": []}
        for _ in range(rounds):
            for k in out:
                out[k] += page.evaluate(f"window.meshsplatViewer.timeDraws(1, {'true' if k == 'float' else 'false'})")
        return out


def screenshot_psnr(index: Path, query: str, ref: np.ndarray, size: int, out_png: Path) -> dict:
    from PIL import Image

    with open_page(index.as_uri() + f"?{query}&ui=0", size, size) as page:
        page.wait_ready(300)
        page.screenshot(out_png)
    img = np.asarray(Image.open(out_png).convert("RGB"), dtype=np.float64)
    subject = (np.abs(ref - 255).max(-1) > 2) | (np.abs(img - 255).max(-1) > 2)
    return {"full_db": psnr(img, ref), "subject_db": psnr(img[subject], ref[subject])}


def render_ref(av: Avatar, verts, cam: dict, size: int) -> np.ndarray:
    camera = Camera(torch.tensor(cam["viewmat"]).float(), torch.tensor(cam["K"]).float(), size, size)
    ref = av.render(torch.as_tensor(verts).float(), camera, background=torch.ones(3)).image
    return ref.detach().clamp(0, 1).numpy() * 255


def bright_key_avatar(mesh: TriMesh, n: int, light: float) -> Avatar:
    """Albedos 0.3-0.8, opacity 0.8, a low ambient irradiance plus an aligned key light of RGB intensity
    ``light`` from (0.6, 0.3, 0.75) (tests/viewer/test_viewer.py's key_shading with a brighter light)."""
    g = torch.Generator().manual_seed(0)
    p = init_params(
        mesh,
        n,
        init_opacity=0.8,
        generator=g,
        colors_fn=lambda f, uv: 0.3 + 0.5 * torch.rand(f.shape[0], 3, generator=g),
    )
    coeffs = torch.zeros(9, 3)
    coeffs[0] = torch.tensor([0.35, 0.35, 0.4]) / 0.28209479177387814
    coeffs[1] = torch.tensor([0.1, 0.1, 0.15])
    key = torch.nn.functional.normalize(torch.tensor([0.6, 0.3, 0.75]), dim=0)[None]
    shading = Shading(
        coeffs,
        "phong",
        occlusion="key",
        directions=16,
        grid=64,
        key=key,
        key_stage=KEY_STAGES,
        light=torch.full((1, 3), light),
    )
    return Avatar(mesh, p, shading=shading)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="20k Gaussians at 256² only, fewer draws")
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    if find_chromium() is None:
        sys.exit("chromium is not installed")
    torch.set_num_threads(1)
    cases = [(20_000, 256)] if args.quick else [(20_000, 256), (20_000, 800), (100_000, 800)]
    rounds = 6 if args.quick else 15
    rows, acc = [], []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        mesh, frames = cesium(60)
        for n, size in cases:
            av = random_avatar(mesh, n, shaded=True)
            b = tmp / f"t{n}-{size}"
            index = write_viewer_bundle(av, frames, b, camera={"width": size, "height": size})
            times = time_draws(index, "&frame=20", size, rounds)
            row = {"gaussians": n, "size": size, "draws": len(times["float"])}
            for k in PATHS:
                row[f"{k}_ms"] = statistics.median(times[k])
            row["paired_diff_ms"] = statistics.median(
                [f - e for f, e in zip(times["float"], times["8-bit"], strict=True)]
            )
            row["times"] = times
            rows.append(row)
            print(
                f"{n:>7,d} G {size}²: float {row['float_ms']:.1f} ms, 8-bit {row['8-bit_ms']:.1f} ms "
                f"(paired difference {row['paired_diff_ms']:+.1f} ms, {row['draws']} draws each)",
                flush=True,
            )
        # accuracy: the shaded avatar (colours mostly <= 1), and CesiumMan under a key light of 1.6
        size = 256 if args.quick else 800
        av = random_avatar(mesh, 20_000, shaded=True, seed=1)
        b = tmp / "acc-frames"
        index = write_viewer_bundle(av, frames, b, camera={"width": size, "height": size})
        h, a = read_viewer_bundle(b)
        ref = render_ref(av, a["vertices"][20], h["camera"], size)
        for k, q in PATHS.items():
            r = screenshot_psnr(index, f"frame=20{q}", ref, size, tmp / "f.png")
            acc.append({"case": f"shaded, 20k Gaussians, vertex frames, frame 20, {size}²", "path": k, **r})
        av = bright_key_avatar(mesh, 6000, 1.6)
        rig = live_rig(av)
        b = tmp / "acc-key"
        index = write_viewer_bundle(av, None, b, rig=rig, camera={"width": 256, "height": 256})
        h = read_viewer_bundle(b)[0]
        clip = next(c for c in h["driver"]["clips"] if c["name"] == h["driver"]["clip"])
        ref = render_ref(av, rig.vertices_at(clip["start"] + 0.8, clip=clip["name"]), h["camera"], 256)
        for k, q in PATHS.items():
            r = screenshot_psnr(index, f"time=0.8{q}", ref, 256, tmp / "k.png")
            acc.append({"case": "CesiumMan live glTF, key light 1.6, 6k Gaussians, t = 0.8 s, 256²", "path": k, **r})
        for r in acc:
            print(
                f"{r['case']} [{r['path']}]: full {r['full_db']:.1f} dB, subject {r['subject_db']:.1f} dB", flush=True
            )
    print("\nmedian time of one frame drawn and waited for (SwiftShader on this CPU; same run)")
    print("\n| Gaussians | canvas | float target + clamp pass | 8-bit canvas (before) | paired difference |")
    print("|---|---|---|---|---|")
    for r in rows:
        d = r["paired_diff_ms"]
        print(
            f"| {r['gaussians'] // 1000}k | {r['size']}² | {r['float_ms']:.1f} ms | {r['8-bit_ms']:.1f} ms | "
            f"{d:+.1f} ms ({100 * d / r['8-bit_ms']:+.0f}%) |"
        )
    print("\n| case | blending | PSNR full frame | PSNR subject |")
    print("|---|---|---|---|")
    for r in acc:
        print(f"| {r['case']} | {r['path']} | {r['full_db']:.1f} dB | {r['subject_db']:.1f} dB |")
    out = Path(args.out) if args.out else results_path("viewer_float" + ("-quick" if args.quick else ""))
    out.write_text(json.dumps({"machine": machine_info(), "rows": rows, "accuracy": acc}, indent=1))
    print(f"saved {out}")


if __name__ == "__main__":
    main()
