"""Benchmark the player in a real headless browser (Chromium, SwiftShader WebGL2), with the page's own
timers: per-frame main-thread time and worker sort time while playing, first complete frame, page
size; and the shaded page's screenshot against ``avatar.render`` for each driver kind.

Timing cases (CesiumMan, 3,273 vertices; random shaded avatars at 100k and 500k Gaussians): vertex
frames (60 baked frames) and live glTF (skin evaluated in the page); baseline in the same run (at
100k): the same Gaussians without shading or view-dependent SH (the page's colour path before it
shaded). 20 frames timed at 100k, 8 at 500k (SwiftShader rasterizes 500k splats slowly on a CPU).
The page records ``window.meshsplatViewer.timings``: ``main`` (its requestAnimationFrame callback:
advance the clock, pose the driver, uploads, GPU passes and draw calls issued) and ``sort`` (the
worker's job, timed inside the worker); ``firstReadyMs``: navigation start to the first frame drawn
in its own sorted order. Under SwiftShader the GPU work runs on the CPU, so frame rates say nothing
about a real GPU; main-thread and worker times are CPU work either way.

Accuracy: a shaded avatar (learned irradiance, SH degree 1 in the triangle frame) at 20k Gaussians,
800², against ``avatar.render`` of the same pose and camera: vertex frames (CesiumMan, frame 20),
live glTF (CesiumMan, t = 0.8 s), live blendshapes (the ICT FaceKit head, talking frame 10); PSNR on
the full frame and on the subject (pixels either image draws).

Usage: python bench/viewer.py [--quick] [--out bench/results/viewer-<host>.json]
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import torch

from _machine import machine_info, results_path
from meshsplat.camera import Camera
from meshsplat.gaussians import Avatar
from meshsplat.gaussians.params import make_params
from meshsplat.gaussians.shading import Shading
from meshsplat.mesh import TriMesh
from meshsplat.paths import assets_dir
from meshsplat.viewer import bundle as bundle_mod
from meshsplat.viewer import read_viewer_bundle, write_viewer_bundle

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))  # the headless-Chromium driver the browser tests use
from _browser import find_chromium, open_page  # noqa: E402


def page_code_at(rev: str) -> str:
    """The page code (viewer.js) of commit ``rev``."""
    path = f"{rev}:src/meshsplat/viewer/static/viewer.js"
    return subprocess.run(["git", "show", path], cwd=ROOT, capture_output=True, text=True, check=True).stdout


def node_or_exit() -> str:
    """The ``node`` executable (the player's code run outside a browser), or exit saying it is missing."""
    node = shutil.which("node")
    if node is None:
        sys.exit("node is not installed")
    return node


def meshsplat_with_src(argv: list[str], src: Path | None) -> None:
    """Run ``meshsplat ARGV`` in a fresh process on another checkout's ``src`` (None: this one's), e.g. a
    baseline page written by that checkout's bundle writer."""
    code = f"from meshsplat.cli.main import main; raise SystemExit(main({argv!r}))"
    env = dict(os.environ, PYTHONPATH=str(src or ROOT / "src"))
    subprocess.run([sys.executable, "-c", code], env=env, check=True, capture_output=True)


def require_sparse_rigs(viewer_js: str, rev: str) -> None:
    """Exit with a note when ``viewer_js`` (the page of ``rev``) cannot read the blend-shape rigs today's
    writer stores (``float16-sparse``, since ca35bdb): such a baseline needs its own writer (``--before-src``)."""
    if "float16-sparse" not in viewer_js:
        raise SystemExit(
            f"the page of {rev} reads no float16-sparse blend-shape rigs (today's bundle writer): give "
            f"--before-src a checkout of {rev}'s src, or a --before-rev from ca35bdb on"
        )


@contextlib.contextmanager
def page_code(viewer_js: str | None) -> Iterator[None]:
    """Within: bundles are written with ``viewer_js`` as their page code (another commit's viewer.js, a
    baseline in the same run); None: today's."""
    static = bundle_mod._STATIC
    if viewer_js is not None:
        tmp = Path(tempfile.mkdtemp(prefix="meshsplat-static-"))
        shutil.copytree(static, tmp, dirs_exist_ok=True)
        (tmp / "viewer.js").write_text(viewer_js, encoding="utf-8")
        bundle_mod._STATIC = tmp
    try:
        yield
    finally:
        bundle_mod._STATIC = static
        if viewer_js is not None:
            shutil.rmtree(tmp, ignore_errors=True)


SIZE = 256  # timing viewport (CSS px, device pixel ratio 1); main-thread and sort work do not depend on it


def random_avatar(mesh: TriMesh, n: int, shaded: bool, seed: int = 0) -> Avatar:
    """n Gaussians spread over the mesh by area, small offsets, random rotations and colours; ``shaded``:
    a coloured directional irradiance and SH degree 1 in the triangle frame."""
    rng = np.random.default_rng(seed)
    v, f = mesh.vertices.double().numpy(), mesh.faces.numpy()
    area = 0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)
    face = rng.choice(len(f), n, p=area / area.sum())
    uv = rng.uniform(0, 1, (n, 2))
    flip = uv.sum(1) > 1
    uv[flip] = 1 - uv[flip]
    s = math.sqrt(area.sum() / n)
    t = lambda x: torch.from_numpy(np.asarray(x, np.float32))  # noqa: E731
    params = make_params(
        torch.from_numpy(face),
        t(uv),
        d=t(rng.normal(0, 0.2 * s, n)),
        log_scale=t(np.log(s * rng.uniform(0.5, 1.5, (n, 3)))),
        rotation=t(rng.normal(size=(n, 4))),
        opacity_logit=t(rng.normal(1, 1, n)),
        sh0=t(rng.normal(0, 0.5, (n, 1, 3))),
        shN=t(rng.normal(0, 0.15, (n, 3, 3))) if shaded else None,
    )
    if not shaded:
        return Avatar(mesh, params)
    coeffs = torch.zeros(9, 3)
    coeffs[0] = torch.tensor([2.4, 2.2, 2.0])
    coeffs[1] = torch.tensor([0.9, 0.7, 0.4])
    coeffs[3] = torch.tensor([0.8, 0.9, 1.1])
    coeffs[6] = torch.tensor([-0.3, 0.1, 0.2])
    return Avatar(mesh, params, shading=Shading(coeffs), sh_frame="triangle")


def cesium(frames: int):
    from meshsplat.animation import AnimationSource, load_animation
    from meshsplat.drivers import GltfDriver

    glb = assets_dir() / "gltf" / "CesiumMan.glb"
    drv = GltfDriver(glb, fps=25)
    mesh = TriMesh(drv.rest_vertices(), drv.faces)
    seq = load_animation(AnimationSource("gltf", glb, fps=25), mesh).vertex_frames()
    return mesh, [seq[i % len(seq)] for i in range(frames)]


def live_rig(av: Avatar):
    from meshsplat.viewer.rig import avatar_driver

    return avatar_driver(av, assets_dir() / "gltf" / "CesiumMan.glb")


def play_and_time(index: Path, min_frames: int, timeout: float) -> dict:
    """Open the page paused (its first complete frame: drawn in its own sorted order), press play, wait
    until it has drawn ``min_frames`` frames (or ``timeout`` s), read its timers."""
    with open_page(index.as_uri() + "?ui=0&play=0", SIZE, SIZE) as page:
        page.wait_ready(timeout)
        start = page.evaluate("window.meshsplatViewer.timings.main.length")
        sorts = page.evaluate("window.meshsplatViewer.timings.sort.length")
        page.evaluate("document.getElementById('play').click()")
        deadline = time.monotonic() + timeout
        while page.evaluate("window.meshsplatViewer.timings.main.length") - start < min_frames:
            if time.monotonic() > deadline:
                break
            time.sleep(0.5)
        t = json.loads(page.evaluate("JSON.stringify(window.meshsplatViewer.timings)"))
    main, sort = t["main"][start:], t["sort"][sorts:]  # while playing
    med = lambda a: statistics.median(a) if a else float("nan")  # noqa: E731
    p90 = lambda a: sorted(a)[int(0.9 * (len(a) - 1))] if a else float("nan")  # noqa: E731
    return {
        "main_ms": med(main),
        "main_p90_ms": p90(main),
        "sort_ms": med(sort),
        "sort_min_ms": min(sort) if sort else float("nan"),
        "frames": len(main),
        "sorts": len(sort),
        "first_ready_ms": t["firstReadyMs"],
    }


def psnr(img: np.ndarray, ref: np.ndarray) -> float:
    return float(10 * np.log10(255.0**2 / max(((img - ref) ** 2).mean(), 1e-10)))


def compare(index: Path, query: str, av: Avatar, verts: torch.Tensor, size: int, out_png: Path) -> dict:
    """Screenshot of the page at ``query`` vs avatar.render of ``verts`` with the bundle's camera."""
    from PIL import Image

    cam = read_viewer_bundle(index.parent)[0]["camera"]
    camera = Camera(torch.tensor(cam["viewmat"]).float(), torch.tensor(cam["K"]).float(), size, size)
    ref = av.render(torch.as_tensor(verts).float(), camera, background=torch.ones(3)).image
    ref = ref.detach().clamp(0, 1).numpy() * 255
    with open_page(index.as_uri() + f"?{query}&ui=0", size, size) as page:
        page.wait_ready(300)
        page.screenshot(out_png)
    img = np.asarray(Image.open(out_png).convert("RGB"), dtype=np.float64)
    subject = (np.abs(ref - 255).max(-1) > 2) | (np.abs(img - 255).max(-1) > 2)
    return {
        "full_db": psnr(img, ref),
        "subject_db": psnr(img[subject], ref[subject]),
        "subject_fraction": float(subject.mean()),
    }


def accuracy(tmp: Path, n: int, size: int) -> list[dict]:
    from meshsplat.drivers import BlendshapeDriver

    rows = []
    mesh, frames = cesium(60)
    av = random_avatar(mesh, n, shaded=True, seed=1)
    b = tmp / "acc-frames"
    write_viewer_bundle(av, frames, b, camera={"width": size, "height": size})
    verts = torch.from_numpy(read_viewer_bundle(b)[1]["vertices"][20])  # the int16 vertices the page draws
    rows.append(
        {
            "driver": "vertex frames",
            "case": "CesiumMan, frame 20",
            **compare(b / "index.html", "frame=20", av, verts, size, tmp / "f.png"),
        }
    )
    rig = live_rig(av)
    b = tmp / "acc-gltf"
    write_viewer_bundle(av, None, b, rig=rig, camera={"width": size, "height": size})
    clip = read_viewer_bundle(b)[0]["driver"]["clips"][0]
    verts = rig.vertices_at(clip["start"] + 0.8, clip=clip["name"])
    rows.append(
        {
            "driver": "live glTF",
            "case": "CesiumMan, t = 0.8 s",
            **compare(b / "index.html", "time=0.8", av, verts, size, tmp / "g.png"),
        }
    )
    drv = BlendshapeDriver.from_npz(None)
    drv.talking_sequence(20, 25.0)
    head = random_avatar(TriMesh(drv.neutral, drv.faces), n, shaded=True, seed=2)
    b = tmp / "acc-blend"
    write_viewer_bundle(head, None, b, fps=25.0, rig=drv, camera={"width": size, "height": size})
    verts = drv.pose(drv.weights[10], drv.rotations[10], drv.translations[10])
    rows.append(
        {
            "driver": "live blendshapes",
            "case": "ICT FaceKit head, talking frame 10",
            **compare(b / "index.html", "time=0.4", head, verts, size, tmp / "h.png"),
        }
    )
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="20k Gaussians, few frames, accuracy at 256²")
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    if find_chromium() is None:
        sys.exit("chromium is not installed")
    torch.set_num_threads(1)
    counts = [20_000] if args.quick else [100_000, 500_000]
    min_frames = {20_000: 10, 100_000: 20, 500_000: 8}  # SwiftShader draws 500k slowly on a CPU
    rows, acc = [], []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        mesh, frames = cesium(60)
        for n in counts:
            for shaded in (False, True) if n <= 100_000 else (True,):  # the baseline at 100k (and quick)
                av = random_avatar(mesh, n, shaded)
                for driver in ("frames", "live glTF"):
                    if driver == "live glTF" and not shaded:
                        continue  # the baseline: vertex frames, unshaded
                    b = tmp / f"{driver}-{n}-{shaded}"
                    if driver == "frames":
                        index = write_viewer_bundle(av, frames, b)
                    else:
                        index = write_viewer_bundle(av, None, b, rig=live_rig(av))
                    r = play_and_time(index, min_frames[n], timeout=300)
                    row = {
                        "driver": driver,
                        "gaussians": n,
                        "shaded": shaded,
                        "index_html_bytes": index.stat().st_size,
                        "avatar_bin_bytes": (b / "avatar.bin").stat().st_size,
                        **r,
                    }
                    rows.append(row)
                    print(
                        f"{driver:9s} {n:>7,d} G {'shaded' if shaded else 'plain ':6s}: main {r['main_ms']:.2f} ms "
                        f"(p90 {r['main_p90_ms']:.2f}, {r['frames']} frames), sort {r['sort_ms']:.2f} ms "
                        f"({r['sorts']} sorts), first frame {r['first_ready_ms']:.0f} ms, "
                        f"page {row['index_html_bytes'] / 1e6:.1f} MB",
                        flush=True,
                    )
                    shutil.rmtree(b)
        acc = accuracy(tmp, 20_000, 256 if args.quick else 800)
    print("\nmedian over the frames drawn while playing (page timers; SwiftShader, CPU-only machine)")
    print("\n| driver | Gaussians | shading | main thread / frame (p90) | worker sort | first frame | index.html |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        print(
            f"| {r['driver']} | {r['gaussians'] // 1000}k | {'shaded, SH 1' if r['shaded'] else 'none (baseline)'} | "
            f"{r['main_ms']:.2f} ({r['main_p90_ms']:.2f}) ms | {r['sort_ms']:.2f} ms | "
            f"{r['first_ready_ms'] / 1000:.1f} s | {r['index_html_bytes'] / 1e6:.1f} MB |"
        )
    print("\n| driver | case | PSNR full frame | PSNR subject |")
    print("|---|---|---|---|")
    for a in acc:
        print(f"| {a['driver']} | {a['case']} | {a['full_db']:.1f} dB | {a['subject_db']:.1f} dB |")
    out = Path(args.out) if args.out else results_path("viewer-browser" + ("-quick" if args.quick else ""))
    out.write_text(json.dumps({"machine": machine_info(), "viewport": SIZE, "rows": rows, "accuracy": acc}, indent=1))
    print(f"saved {out}")


if __name__ == "__main__":
    main()
