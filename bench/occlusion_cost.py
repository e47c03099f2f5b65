"""What shading with occlusion (shading.occlusion=directions, key) costs per frame, on the CesiumMan mesh.

    python bench/occlusion_cost.py                 # 10k Gaussians, 256 px, 16/32 directions x 32/64 cells
    python bench/occlusion_cost.py --asset RobotExpressive   # another bundled glTF (longer triangles)
    python bench/occlusion_cost.py --tiny          # seconds, to check the script

Times, interleaved and in the same process (median of --repeats), the visibility alone
(``meshsplat.mesh.visibility``), ``Avatar.compose`` and a whole ``Avatar.render`` for today's shading
(``sh2``) and for each occlusion setting (the key: hard, and soft with 12 maps at grid 64, 96 and 128), on poses of the bundled CesiumMan walk (4672 triangles).
The soft key at grid 64 and 96 is timed twice: with the shadow maps compiled (numba, what CPU tensors use
when it is installed) and in pure torch (``, torch maps``: ``mesh.visibility`` told numba is missing; the
rasterizer keeps ``--backend``), the baseline of the compiled maps.
Saves bench/results/<name>-<host>.json.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

from _machine import machine_info, results_path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--gaussians", type=int, default=10_000)
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--backend", default="auto")
    ap.add_argument("--name", default="occlusion_cost")
    ap.add_argument("--asset", default="CesiumMan", help="a bundled glTF: CesiumMan, RobotExpressive")
    ap.add_argument("--tiny", action="store_true")
    args = ap.parse_args()
    if args.tiny:
        args.gaussians, args.size, args.repeats = 1000, 64, 2

    import torch

    from _shadow_maps import use_torch_maps
    from meshsplat.camera import Camera
    from meshsplat.drivers import GltfDriver
    from meshsplat.embedding import embed, sample_surface
    from meshsplat.gaussians import Avatar, init_params
    from meshsplat.gaussians.shading import KEY_STAGES, Shading
    from meshsplat.mesh import MeshPose, TriMesh
    from meshsplat.paths import bundled_asset

    torch.set_num_threads(args.threads)
    drv = GltfDriver(bundled_asset(args.asset))
    mesh = TriMesh(drv.rest_vertices(), drv.faces)
    frames = [drv.vertices(i) for i in range(0, drv.num_frames, max(1, drv.num_frames // 4))][:4]
    params = init_params(mesh, args.gaussians, generator=torch.Generator().manual_seed(0))
    lo, hi = mesh.vertices.amin(0), mesh.vertices.amax(0)
    centre, diag = (lo + hi) / 2, float((hi - lo).norm())
    eye = centre + torch.tensor([0.0, 0.0, 1.3 * diag])  # in front (glTF: y up, facing +z)
    fwd = torch.nn.functional.normalize(centre - eye, dim=0)
    up = torch.tensor([0.0, 1.0, 0.0])
    right = torch.nn.functional.normalize(torch.linalg.cross(fwd, up), dim=0)
    down = torch.linalg.cross(fwd, right)
    R = torch.stack([right, down, fwd])
    viewmat = torch.eye(4)
    viewmat[:3, :3], viewmat[:3, 3] = R, -R @ eye
    f = args.size * 1.2
    K = torch.tensor([[f, 0, args.size / 2], [0, f, args.size / 2], [0, 0, 1.0]])
    cam = Camera(viewmat, K, args.size, args.size)

    settings = {"sh2 (today)": None}
    for k in (16, 32):
        for g in (32, 64):
            settings[f"occl K={k} grid={g}"] = (k, g, 0, 0.0)
    settings["key, rings (7)"] = (16, 64, 1, 0.0)  # shading.occlusion=key while it narrows the direction
    settings["key (1 light)"] = (16, 64, KEY_STAGES, 0.0)  # shading.occlusion=key once aligned, a hard shadow
    settings["key soft (12 maps)"] = (16, 64, KEY_STAGES, 8.0)  # aligned, shading.key_soft=8
    settings["key soft, grid 64, torch maps"] = (16, 64, KEY_STAGES, 8.0)
    settings["key soft, grid 96"] = (16, 96, KEY_STAGES, 8.0)  # finer maps (shading.grid)
    settings["key soft, grid 96, torch maps"] = (16, 96, KEY_STAGES, 8.0)
    settings["key soft, grid 128"] = (16, 128, KEY_STAGES, 8.0)
    avatars = {}
    for name, s in settings.items():
        kind = "directions" if s is None or not s[2] else "key"
        sh = Shading() if s is None else Shading(occlusion=kind, directions=s[0], grid=s[1], key_soft=s[3])
        if sh.light is not None:
            sh.light.fill_(0.2)
        for _ in range(0 if s is None else s[2]):
            sh.align_key()
        avatars[name] = Avatar(mesh, params, shading=sh)

    face, uv = sample_surface(mesh.vertices, mesh.faces, args.gaussians, generator=torch.Generator().manual_seed(1))
    times: dict[str, dict[str, list[float]]] = {n: {"visibility": [], "compose": [], "render": []} for n in settings}
    with torch.no_grad():
        for _ in range(args.repeats + 1):  # the first round warms up (numba compile, allocator)
            for name, av in avatars.items():
                use_torch_maps(name.endswith("torch maps"))
                for v in frames:
                    t = {}
                    if av.shading is not None and av.shading.directions is not None:
                        pose = MeshPose.from_vertices(mesh, v)
                        pts, n = embed(pose, face, uv, torch.zeros(len(face)))
                        t0 = time.perf_counter()
                        av.shading.visibility(pose, pts, n)
                        t["visibility"] = time.perf_counter() - t0
                    t0 = time.perf_counter()
                    av.compose(v)
                    t["compose"] = time.perf_counter() - t0
                    t0 = time.perf_counter()
                    av.render(v, cam, torch.ones(3), backend=args.backend)
                    t["render"] = time.perf_counter() - t0
                    for key, val in t.items():
                        times[name][key].append(val)
    skip = len(frames)
    rows = {n: {k: 1000 * statistics.median(v[skip:]) for k, v in t.items() if len(v) > skip} for n, t in times.items()}
    base = rows["sh2 (today)"]["render"]
    print(
        f"{args.asset} ({mesh.num_faces} triangles), {args.gaussians} Gaussians, {args.size} px, backend {args.backend}, "
        f"{args.threads} thread(s); median ms per frame over {args.repeats} x {len(frames)} poses"
    )
    print(f"{'setting':<32}{'visibility':>12}{'compose':>10}{'render':>10}{'render x':>10}")
    for n, r in rows.items():
        vis = f"{r['visibility']:.1f}" if "visibility" in r else "-"
        print(f"{n:<32}{vis:>12}{r['compose']:>10.1f}{r['render']:>10.1f}{r['render'] / base:>10.2f}")
    out = results_path(args.name)
    out.write_text(json.dumps({"machine": machine_info(), "args": vars(args), "ms": rows}, indent=2) + "\n")
    print(f"saved {out}")


if __name__ == "__main__":
    main()
