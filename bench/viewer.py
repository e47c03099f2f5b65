"""Benchmark the browser viewer's CPU side under Node (no browser): per-frame main-thread time and
worker sort time, today's player vs the previous one (commit bae8ae0: posing every Gaussian in JS on
the main thread), in the same run; plus bundle sizes.

Cases: CesiumMan (3,273 vertices, its glTF clip baked to 60 frames, and live), and a larger mesh
(a deformed UV sphere with about 80k vertices, 60 frames of analytic motion), each with 20k, 100k
and 500k Gaussians.

New player, main thread per frame: FramePoser (vertex frames: decode the frame's vertices; live
glTF: evaluate the clip's node matrices and morph weights). The texture uploads (16 B per vertex,
or 48 B per joint), the GPU passes and the order upload (4 B per Gaussian when a sort arrives) are
GPU-driver work that Node cannot time. Worker: sortJob (live glTF: skinning; vertex normals, centre
depths, 16-bit counting sort).
Old player, main thread per frame: poseGaussians + sortByDepth + packing 13 floats per Gaussian
(its SplatRenderer.upload without the WebGL call).

Usage: python bench/viewer.py [--quick] [--out bench/results/viewer-<host>.json]
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import math
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch

from _machine import machine_info, results_path
from meshsplat.gaussians import Avatar
from meshsplat.gaussians.params import make_params
from meshsplat.mesh import TriMesh
from meshsplat.paths import assets_dir
from meshsplat.viewer import write_viewer_bundle

OLD_COMMIT = "bae8ae0"
ROOT = Path(__file__).resolve().parents[1]
NODE_SCRIPT = Path(__file__).resolve().parent / "_viewer_frame.mjs"


def old_bundle_module(tmp: Path):
    """The previous bundle writer and viewer (git show OLD_COMMIT), importable from a temp folder."""
    folder = tmp / "old_viewer"
    (folder / "static").mkdir(parents=True)
    for rel in ("bundle.py", "static/viewer.js", "static/index.html"):
        src = subprocess.run(
            ["git", "-C", str(ROOT), "show", f"{OLD_COMMIT}:src/meshsplat/viewer/{rel}"],
            check=True,
            capture_output=True,
            text=True,
        ).stdout
        (folder / rel).write_text(src)
    spec = importlib.util.spec_from_file_location("old_viewer_bundle", folder / "bundle.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def random_avatar(mesh: TriMesh, n: int, seed: int = 0) -> Avatar:
    """n Gaussians spread over the mesh by area, small offsets, random rotations and colours."""
    rng = np.random.default_rng(seed)
    v, f = mesh.vertices.double().numpy(), mesh.faces.numpy()
    area = 0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)
    face = rng.choice(len(f), n, p=area / area.sum())
    uv = rng.uniform(0, 1, (n, 2))
    flip = uv.sum(1) > 1
    uv[flip] = 1 - uv[flip]
    s = math.sqrt(area.sum() / n)
    q = rng.normal(size=(n, 4))
    t = lambda x: torch.from_numpy(np.asarray(x, np.float32))  # noqa: E731
    params = make_params(
        torch.from_numpy(face),
        t(uv),
        d=t(rng.normal(0, 0.2 * s, n)),
        log_scale=t(np.log(s * rng.uniform(0.3, 1.0, (n, 3)))),
        rotation=t(q),
        opacity_logit=t(rng.normal(1, 1, n)),
        sh0=t(rng.normal(0, 0.5, (n, 1, 3))),
    )
    return Avatar(mesh, params)


def cesium(frames: int):
    from meshsplat.drivers import AnimationSource, GltfDriver, load_animation

    glb = assets_dir() / "gltf" / "CesiumMan.glb"
    drv = GltfDriver(glb, fps=25)
    mesh = TriMesh(drv.rest_vertices(), drv.faces)
    probe = Avatar(
        mesh,
        make_params(
            torch.zeros(1, dtype=torch.long),
            torch.full((1, 2), 0.3),
            log_scale=torch.zeros(1, 3),
            opacity_logit=torch.zeros(1),
            sh0=torch.zeros(1, 1, 3),
        ),
    )
    seq = load_animation(AnimationSource("gltf", glb, fps=25), probe).vertex_frames()
    return mesh, [seq[i % len(seq)] for i in range(frames)]


def live_rig(av):
    from meshsplat.viewer.rig import avatar_driver

    return avatar_driver(av, assets_dir() / "gltf" / "CesiumMan.glb")


def sphere(frames: int):
    import trimesh

    s = trimesh.creation.uv_sphere(count=[201, 201])
    v = torch.tensor(s.vertices, dtype=torch.float64)
    mesh = TriMesh(v.float(), torch.tensor(s.faces))
    out = []
    for i in range(frames):
        a = 2 * math.pi * i / frames
        w = v.clone()
        w[:, 0] += 0.2 * torch.sin(3 * v[:, 1] + a)
        w[:, 2] += 0.15 * torch.cos(2 * v[:, 0] - a)
        out.append(w.float())
    return mesh, out


def node_bench(viewer_js: Path, bundle: Path, mode: str, frames: int) -> dict:
    r = subprocess.run(
        ["node", str(NODE_SCRIPT), str(viewer_js), str(bundle), mode, str(frames)],
        check=True,
        capture_output=True,
        text=True,
        timeout=3600,
    )
    return json.loads(r.stdout)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="20k Gaussians, CesiumMan only, few frames")
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    if shutil.which("node") is None:
        sys.exit("node is not installed")
    torch.set_num_threads(1)
    counts = [20_000] if args.quick else [20_000, 100_000, 500_000]
    timed = 5 if args.quick else 20
    meshes = {"CesiumMan": cesium(60)} if args.quick else {"CesiumMan": cesium(60), "sphere-80k": sphere(60)}
    rows, sizes = [], []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        old = old_bundle_module(tmp)
        new_js = ROOT / "src/meshsplat/viewer/static/viewer.js"
        old_js = tmp / "old_viewer/static/viewer.js"
        for name, (mesh, frames) in meshes.items():
            for n in counts:
                av = random_avatar(mesh, n)
                nb, ob = tmp / f"new-{name}-{n}", tmp / f"old-{name}-{n}"
                write_viewer_bundle(av, frames, nb)
                old.write_viewer_bundle(av, frames, ob)
                if name == "CesiumMan" and n in (20_000, 100_000):
                    sizes.append(
                        {
                            "case": f"{name} 60 frames, {n // 1000}k Gaussians",
                            **{
                                f"{k}_{f}": (d / f).stat().st_size
                                for k, d in (("old", ob), ("new", nb))
                                for f in ("avatar.bin", "index.html")
                            },
                        }
                    )
                new = node_bench(new_js, nb, "new", timed)
                prev = node_bench(old_js, ob, "old", max(3, timed // 4) if n >= 500_000 else timed)
                rows.append(
                    {
                        "mesh": name,
                        "driver": "frames",
                        "vertices": mesh.num_vertices,
                        "gaussians": n,
                        "new": new,
                        "old": prev,
                    }
                )
                if name == "CesiumMan":
                    lb = tmp / f"live-{n}"
                    write_viewer_bundle(av, None, lb, rig=live_rig(av))
                    if n in (20_000, 100_000):
                        sizes[-1].update({f"live_{f}": (lb / f).stat().st_size for f in ("avatar.bin", "index.html")})
                    rows.append(
                        {
                            "mesh": name,
                            "driver": "live glTF",
                            "vertices": mesh.num_vertices,
                            "gaussians": n,
                            "new": node_bench(new_js, lb, "new", timed),
                            "old": None,
                        }
                    )
                    shutil.rmtree(lb)
                for r in rows[-2:] if name == "CesiumMan" else rows[-1:]:
                    o = r["old"]
                    print(
                        f"{name:10s} {r['driver']:9s} {n:>7,d} G: main old "
                        f"{o['main_ms'] if o else float('nan'):8.2f} ms  new {r['new']['main_ms']:6.2f} ms | sort old "
                        f"(main) {o['sort_ms'] if o else float('nan'):6.2f} ms  new (worker) {r['new']['sort_ms']:6.2f} ms",
                        flush=True,
                    )
                shutil.rmtree(nb)
                shutil.rmtree(ob)
    ms = lambda r, k: f"{r[k]:.2f} ({r[k.replace('_ms', '_min_ms')]:.2f}) ms" if r else "n/a"  # noqa: E731
    print("\nmedian (min) over the timed frames")
    print(
        "\n| mesh (vertices) | driver | Gaussians | main thread / frame, old | new | sort, old (main thread) | new (worker) |"
    )
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        print(
            f"| {r['mesh']} ({r['vertices']:,}) | {r['driver']} | {r['gaussians'] // 1000}k | {ms(r['old'], 'main_ms')} | "
            f"**{ms(r['new'], 'main_ms')}** | {ms(r['old'], 'sort_ms')} | **{ms(r['new'], 'sort_ms')}** |"
        )
    print("\n| bundle | avatar.bin old | new | new, live glTF | index.html old | new | new, live glTF |")
    print("|---|---|---|---|---|---|---|")
    mb = lambda s, k: f"{s[k] / 1e6:.2f} MB" if k in s else "n/a"  # noqa: E731
    for s in sizes:
        print(
            f"| {s['case']} | {mb(s, 'old_avatar.bin')} | {mb(s, 'new_avatar.bin')} | {mb(s, 'live_avatar.bin')} | "
            f"{mb(s, 'old_index.html')} | {mb(s, 'new_index.html')} | {mb(s, 'live_index.html')} |"
        )
    out = Path(args.out) if args.out else results_path("viewer" + ("-quick" if args.quick else ""))
    out.write_text(
        json.dumps(
            {
                "machine": machine_info(),
                "node": subprocess.run(["node", "--version"], capture_output=True, text=True).stdout.strip(),
                "rows": rows,
                "sizes": sizes,
            },
            indent=1,
        )
    )
    print(f"saved {out}")


if __name__ == "__main__":
    main()
