"""What the camera check at the door costs (``data.camera_check``, issues 44 and 52), per frame.

    python bench/camera_check_cost.py                # 170 CesiumMan frames at 540 px (PeopleSnapshot-sized)
    python bench/camera_check_cost.py --frames 24 --resolution 128 --repeats 3   # seconds

Two captures of CesiumMan:

- ``full body``: ``meshsplat synth``'s capture (orbiting cameras, the whole body in view): most frames pass
  on their vertices alone;
- ``close-up``: the belly filling the image from 0.5 m (under 10% of the vertices inside it), rendered with
  the project's own triangle rasterizer so every mask matches its camera: every frame takes the close-up
  path (the mesh's triangles projected onto the mask grid and compared with it both ways, the shrunk
  projections tried; without masks, the projected mesh's cover and the camera's winding number).

Each is opened alternately with the masks checked (every mask decoded, pooled and compared; the reader's
own checks, which decode every mask for emptiness, included) and with ``check_masks=False`` (geometry only,
as ``render`` and ``view`` open a capture), ``--repeats`` times each, one thread; then the check alone
(``check_cameras``, masks decoded as the door does) is timed the same way. Wall-clock (``perf_counter``) and
CPU time of this process (``process_time``) are recorded: on a machine shared with other jobs the CPU time is
the steadier number. Prints a table of medians per frame and saves bench/results/camera_check_cost-<host>.json
with the machine, its load before and after, and every repeat.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from _machine import machine_info, results_path
from meshsplat.camera import intrinsics, look_at
from meshsplat.data import open_dataset
from meshsplat.data.camera_check import check_cameras
from meshsplat.data.writer import DatasetWriter
from meshsplat.drivers import GltfDriver
from meshsplat.paths import assets_dir
from meshsplat.synth import synthesize
from meshsplat.synth.raster import rasterize_triangles


def close_up_capture(root: Path, frames: int, resolution: int) -> Path:
    """CesiumMan's belly from 0.5 m (40 degrees; under 10% of the vertices in the image), posed along its walk;
    the image is the rendered mask."""
    d = GltfDriver(assets_dir() / "gltf" / "CesiumMan.glb")
    faces = d.faces.numpy()
    K = intrinsics(resolution, resolution, 40.0)
    vm = look_at(np.array([0.0, 0.9, 0.5]), np.array([0.0, 0.9, 0.0]), up=(0.0, 1.0, 0.0))
    w = DatasetWriter(root, d.vertices(0).numpy(), faces)
    w.add_camera("0", K, vm, resolution, resolution)
    for i in range(frames):
        v = d.vertices(i % max(1, d.num_frames)).numpy().astype(np.float64)
        cam = v @ vm[:3, :3].T + vm[:3, 3]
        frags = rasterize_triangles(
            torch.from_numpy(cam).float(), torch.from_numpy(faces), torch.from_numpy(K).float(), resolution, resolution
        )
        mask = frags.mask.numpy()
        img = np.where(mask[..., None], np.array([0.8, 0.5, 0.3]), 1.0)
        w.add_frame(img, "0", vertices=v, mask=mask.astype(np.float32), name=f"{i:04d}")
    w.close()
    return root


def check_alone(ds, masks: bool) -> None:
    """``check_cameras`` as the door calls it (the masks decoded by the dataset's reader)."""
    frames = ds._frames
    found = check_cameras(
        ds._cameras,
        [(str(r["camera"]), int(r["mesh"])) for r in frames],
        ds._verts,
        (lambda i: ds._load_mask(frames[i]).numpy()) if masks else (lambda i: None),
        ds.faces.numpy(),
    )
    assert found.ok, (found.wrong, found.bad_frames)


def timed(fn, repeats: int) -> dict[str, list[float]]:
    out: dict[str, list[float]] = {"wall": [], "cpu": []}
    for _ in range(repeats):
        w0, c0 = time.perf_counter(), time.process_time()
        fn()
        out["wall"].append(time.perf_counter() - w0)
        out["cpu"].append(time.process_time() - c0)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=170)
    ap.add_argument("--resolution", type=int, default=540)
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()
    torch.set_num_threads(1)
    load_before = os.getloadavg()
    results: dict[str, dict] = {}
    with tempfile.TemporaryDirectory() as tmp:
        captures = {
            "full body": synthesize(
                "CesiumMan",
                Path(tmp) / "full",
                frames=args.frames,
                resolution=args.resolution,
                test_frames=0,
                test_views=0,
            ),
            "close-up": close_up_capture(Path(tmp) / "close", args.frames, args.resolution),
        }
        for name, root in captures.items():
            ds = open_dataset(root, check_masks=False)
            n = len(open_dataset(root))  # also: the capture passes the check with its masks
            runs: dict[str, dict[str, list[float]]] = {k: {"wall": [], "cpu": []} for k in ("open", "open_geo")}
            for _ in range(args.repeats):  # alternated, so a change of load hits both alike
                for key, masks in (("open", True), ("open_geo", False)):
                    t = timed(lambda r=root, m=masks: open_dataset(r, check_masks=m), 1)
                    runs[key]["wall"] += t["wall"]
                    runs[key]["cpu"] += t["cpu"]
            runs["check"] = timed(lambda d=ds: check_alone(d, True), args.repeats)
            runs["check_geo"] = timed(lambda d=ds: check_alone(d, False), args.repeats)
            med = {k: {c: statistics.median(v[c]) for c in ("wall", "cpu")} for k, v in runs.items()}
            results[name] = {"frames": n, "seconds": runs, "median_s": med}
    load_after = os.getloadavg()

    def ms(name: str, key: str, clock: str) -> float:
        return 1000 * results[name]["median_s"][key][clock] / results[name]["frames"]

    print(
        f"\n{args.frames} frames at {args.resolution} px, medians of {args.repeats}, 1 thread; "
        f"load {load_before[0]:.1f} before, {load_after[0]:.1f} after"
    )
    print(
        "| capture | open, masks checked | open, geometry only | extra for the masks | check alone | check alone, geometry |"
    )
    print("|---|---|---|---|---|---|")
    for name in results:
        cells = []
        for key in ("open", "open_geo"):
            cells.append(f"{ms(name, key, 'wall'):.1f} ms ({ms(name, key, 'cpu'):.1f} CPU)")
        extra = [ms(name, "open", c) - ms(name, "open_geo", c) for c in ("wall", "cpu")]
        cells.append(f"{extra[0]:.1f} ms ({extra[1]:.1f} CPU)")
        for key in ("check", "check_geo"):
            cells.append(f"{ms(name, key, 'wall'):.2f} ms ({ms(name, key, 'cpu'):.2f} CPU)")
        print(f"| {name} | " + " | ".join(cells) + " |")
    print("(per frame; wall-clock, and the process's CPU time in brackets)")
    out = results_path("camera_check_cost")
    out.write_text(
        json.dumps(
            {
                "machine": machine_info(),
                "load_avg_before": list(load_before),
                "load_avg_after": list(load_after),
                "frames": args.frames,
                "resolution": args.resolution,
                "repeats": args.repeats,
                "captures": results,
                "ms_per_frame": {
                    name: {
                        f"{key}_{clock}": ms(name, key, clock)
                        for key in ("open", "open_geo", "check", "check_geo")
                        for clock in ("wall", "cpu")
                    }
                    for name in results
                },
            },
            indent=2,
        )
        + "\n"
    )
    print(f"saved {out}")


if __name__ == "__main__":
    main()
