"""Cost of the web player's key-light shadow (shading.occlusion=key): the page's per-pose height maps
(``keyShadowMap`` in viewer.js, CPU) under Node, and in a real headless browser (Chromium, SwiftShader
WebGL2) the page's own timers while playing, with the same avatar without the key light as the same-run
baseline.

Node: meshes of 4.7k to 52k triangles (CesiumMan, a UV sphere, CesiumMan subdivided once, the ICT
FaceKit head), each posed in 8 frames (CesiumMan: its walk; the others: a twist), a hard key at grid 64
and 128 and a soft key (``shading.key_soft``: 12 maps) at grid 64 and 96 (the default since
config version 9); ``keyShadowMap`` timed 5 times per frame after 3 warm-up calls; medians over all
calls; the surface sample count it scatters per map. Browser: 20k Gaussians on CesiumMan (vertex frames and live glTF) and on the ICT head (vertex
frames), no key / hard / soft at grid 64 / soft at grid 96 (``soft96``, the default since config
version 9); the page builds the height maps in its shadow worker, and with ``?worker=0`` on the main
thread (as before the worker; that also sorts on the main thread, whose time ``timings.sort``
reports). Per frame while playing, 40 frames each: ``timings.main`` (the whole requestAnimationFrame
callback, main thread) and ``timings.key`` (the height maps of one pose, in the worker or on the main
thread; live glTF: plus the CPU skinning they need).

Usage: python bench/viewer_shadow.py [--quick] [--out bench/results/viewer_shadow-<host>.json]
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from _machine import machine_info, results_path
from meshsplat.gaussians import Avatar
from meshsplat.gaussians.shading import KEY_SOFT_SAMPLES, KEY_STAGES, Shading
from meshsplat.mesh import TriMesh
from meshsplat.paths import assets_dir
from meshsplat.viewer import write_viewer_bundle
from viewer import SIZE, cesium, live_rig, node_or_exit, random_avatar

ROOT = Path(__file__).resolve().parents[1]
VIEWER_JS = ROOT / "src" / "meshsplat" / "viewer" / "static" / "viewer.js"
SOFT_DEG = 8.0  # the soft key's angular radius (shading.key_soft): KEY_SOFT_SAMPLES maps per pose


def key_shading(grid: int, soft: float = 0.0) -> Shading:
    coeffs = torch.zeros(9, 3)
    coeffs[0] = 0.4 / 0.28209479177387814
    key = torch.nn.functional.normalize(torch.tensor([0.6, 0.5, 0.6]), dim=0)[None]
    return Shading(
        coeffs,
        occlusion="key",
        directions=16,
        grid=grid,
        key=key,
        key_stage=KEY_STAGES,
        light=torch.tensor([[1.0, 0.9, 0.8]]),
        key_soft=soft,
    )


def twist(v: torch.Tensor, t: float) -> torch.Tensor:
    y = v[:, 1:2] - v[:, 1].mean()
    a = t * 1.5 * y / max(float(y.abs().max()), 1e-9)
    c, s = torch.cos(a), torch.sin(a)
    return torch.cat([c * v[:, 0:1] + s * v[:, 2:3], v[:, 1:2], -s * v[:, 0:1] + c * v[:, 2:3]], 1)


def meshes(quick: bool) -> list[tuple[str, TriMesh, list[torch.Tensor]]]:
    import trimesh

    out = []
    cm, frames = cesium(8)
    out.append(("CesiumMan", cm, frames))
    sph = trimesh.creation.uv_sphere(count=[72, 72])
    m = TriMesh(torch.tensor(sph.vertices, dtype=torch.float32), torch.tensor(sph.faces))
    out.append(("uv sphere", m, [twist(m.vertices, t) for t in np.linspace(0, 1, 8)]))
    if not quick:
        v, f = trimesh.remesh.subdivide(cm.vertices.double().numpy(), cm.faces.numpy())
        sub = TriMesh(torch.tensor(v, dtype=torch.float32), torch.tensor(f))
        out.append(("CesiumMan subdivided", sub, [twist(sub.vertices, t) for t in np.linspace(0, 1, 8)]))
        from meshsplat.drivers import BlendshapeDriver

        drv = BlendshapeDriver.from_npz(assets_dir() / "ict_facekit" / "ict_face_arkit53.npz")
        ict = TriMesh(drv.neutral, drv.faces)
        out.append(("ICT FaceKit head", ict, [twist(ict.vertices, t) for t in np.linspace(0, 1, 8)]))
    return out


def node_times(bundle: Path) -> dict:
    script = f"""
import {{ decodeBundle, frameVertices, keyShadowMap }} from {json.dumps(VIEWER_JS.as_uri())};
import fs from "fs";
const h = JSON.parse(fs.readFileSync({json.dumps(str(bundle / "avatar.json"))}, "utf8"));
const b = decodeBundle(h, fs.readFileSync({json.dumps(str(bundle / "avatar.bin"))}));
const key = h.shading.key, ms = [];
let m, samples = 0;
for (let t = 0; t < b.T; t++) {{
  const p = Float32Array.from(frameVertices(b, t));
  for (let r = 0; r < 8; r++) {{
    const t0 = performance.now();
    m = keyShadowMap(b.faces, b.V, p, key, m);
    if (r >= 3) ms.push(performance.now() - t0);
  }}
  samples = Math.max(samples, m.samples);
}}
console.log(JSON.stringify({{ ms, samples }}));
"""
    path = bundle / "time.mjs"
    path.write_text(script)
    r = subprocess.run(["node", str(path)], capture_output=True, text=True, check=True)
    return json.loads(r.stdout)


def play(index: Path, min_frames: int, timeout: float, worker: bool = True) -> dict:
    """Open the page paused, press play, wait for ``min_frames`` drawn frames (or ``timeout`` s); the
    medians of its timers while playing (as bench/viewer.py's play_and_time, plus ``timings.key`` and
    ``timings.sort``). ``worker`` False: ``?worker=0`` (height maps and sort on the main thread)."""
    from _browser import open_page

    with open_page(index.as_uri() + "?ui=0&play=0" + ("" if worker else "&worker=0"), SIZE, SIZE) as page:
        page.wait_ready(timeout)
        in_worker = page.evaluate("window.meshsplatViewer.shadowWorker")
        start = {k: page.evaluate(f"window.meshsplatViewer.timings.{k}.length") for k in ("main", "key", "sort")}
        page.evaluate("document.getElementById('play').click()")
        deadline = time.monotonic() + timeout
        while page.evaluate("window.meshsplatViewer.timings.main.length") - start["main"] < min_frames:
            if time.monotonic() > deadline:
                break
            time.sleep(0.5)
        t = json.loads(page.evaluate("JSON.stringify(window.meshsplatViewer.timings)"))
    main, key, sort = (t[k][start[k] :] for k in ("main", "key", "sort"))
    med = lambda a: statistics.median(a) if a else float("nan")  # noqa: E731
    p90 = lambda a: sorted(a)[int(0.9 * (len(a) - 1))] if a else float("nan")  # noqa: E731
    return {
        "maps_in": "-" if in_worker is None else "worker" if in_worker else "main",
        "main_ms": med(main),
        "main_p90_ms": p90(main),
        "key_ms": med(key),
        "sort_ms": med(sort),
        "frames": len(main),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="two meshes, grid 64, no browser")
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    torch.set_num_threads(1)
    node_or_exit()
    rows, browser = [], []
    with tempfile.TemporaryDirectory() as tmp:
        for name, mesh, frames in meshes(args.quick):
            for grid, soft in ((64, 0.0), (64, SOFT_DEG), (96, SOFT_DEG)) + (() if args.quick else ((128, 0.0),)):
                av = Avatar(mesh, random_avatar(mesh, 200, False).params, shading=key_shading(grid, soft))
                folder = Path(tmp) / f"{name}-{grid}-{soft}".replace(" ", "_")
                write_viewer_bundle(av, frames, folder, vertex_encoding="float32")
                t = node_times(folder)
                rows.append(
                    {
                        "mesh": name,
                        "vertices": mesh.num_vertices,
                        "triangles": mesh.num_faces,
                        "grid": grid,
                        "maps": KEY_SOFT_SAMPLES if soft else 1,
                        "samples": t["samples"],
                        "median_ms": statistics.median(t["ms"]),
                        "min_ms": min(t["ms"]),
                        "calls": len(t["ms"]),
                    }
                )
        if not args.quick:
            from _browser import find_chromium

            if find_chromium() is None:
                sys.exit("chromium is not installed (or run with --quick)")
            cm, cm_frames = cesium(60)
            head = next((m, f) for n, m, f in meshes(False) if n == "ICT FaceKit head")
            cases = [("CesiumMan", "frames", cm, cm_frames), ("CesiumMan", "live glTF", cm, None)]
            cases.append(("ICT head", "frames", head[0], [twist(head[0].vertices, t) for t in np.linspace(0, 1, 60)]))
            for name, kind, mesh, frames in cases:
                base = random_avatar(mesh, 20000, True)
                assert base.shading is not None
                for with_key in ("none", "hard", "soft", "soft96"):  # soft96: the default's 96-cell maps
                    sh = key_shading(96 if with_key == "soft96" else 64, 0.0 if with_key == "hard" else SOFT_DEG)
                    if with_key == "none":
                        sh = Shading(base.shading.coeffs)
                    sh.coeffs = base.shading.coeffs.clone()
                    av = Avatar(mesh, base.params, shading=sh, sh_frame="triangle")
                    folder = Path(tmp) / f"page-{name}-{kind}-{with_key}".replace(" ", "_")
                    if kind == "frames":
                        write_viewer_bundle(av, frames, folder, fps=25)
                    else:
                        write_viewer_bundle(av, None, folder, rig=live_rig(av))
                    for worker in (True, False) if with_key != "none" else (True,):
                        timed = play(folder / "index.html", 40, 120.0, worker)
                        browser.append({"mesh": name, "driver": kind, "key": with_key, **timed})
    print("keyShadowMap under Node (median of the timed calls, 8 poses x 5 calls)")
    print(
        f"{'mesh':<22} {'verts':>6} {'tris':>6} {'grid':>4} {'maps':>4} {'samples':>8} {'median ms':>9} {'min ms':>7}"
    )
    for r in rows:
        print(
            f"{r['mesh']:<22} {r['vertices']:>6} {r['triangles']:>6} {r['grid']:>4} {r['maps']:>4} {r['samples']:>8}"
            f" {r['median_ms']:>9.2f} {r['min_ms']:>7.2f}"
        )
    if browser:
        print("\npage while playing (20k Gaussians, SwiftShader): medians per frame")
        print(
            f"{'mesh':<10} {'driver':<10} {'key':>5} {'maps in':>7} {'main ms':>8} {'main p90':>8}"
            f" {'shadow maps ms':>14} {'sort ms':>7} {'frames':>6}"
        )
        for r in browser:
            print(
                f"{r['mesh']:<10} {r['driver']:<10} {r['key']!s:>5} {r['maps_in']:>7} {r['main_ms']:>8.2f}"
                f" {r['main_p90_ms']:>8.2f} {r['key_ms']:>14.2f} {r['sort_ms']:>7.2f} {r['frames']:>6}"
            )
    out = args.out or results_path("viewer_shadow")
    out.write_text(json.dumps({"machine": machine_info(), "node": rows, "browser": browser}, indent=1) + "\n")
    print(f"saved {out}")


if __name__ == "__main__":
    main()
