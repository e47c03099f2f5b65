"""Write a self-contained WebGL viewer (open index.html in a browser) animating a trained avatar.

Animation (default: the run's dataset meshes, all stored frames in order):
  --animation dataset [--split NAME]     the dataset's meshes (or those of one split)
  --animation gltf FILE [--clip NAME]    a glTF/GLB clip driving the avatar's mesh
  --animation vertices FILE              a vertex sequence [T,V,3] (.npy, mesh-sequence .npz, OBJ/PLY folder)
  --animation motion FILE                SMPL/SMPL-X motion .npz, FLAME flame_params.json or VHAP
                                         flame_param/ (avatars of SMPL/FLAME captures; baked to frames)
--frames N keeps the first N frames. The page works from file://; --serve also serves the
folder on http://127.0.0.1:PORT until Ctrl-C.

Examples:
  meshsplat view runs/demo --out out/viewer
  meshsplat view runs/demo --animation gltf CesiumMan.glb --frames 60 --out out/viewer
"""
from __future__ import annotations

import argparse
from pathlib import Path

from meshsplat.errors import MeshsplatError

__all__ = ["add_arguments", "run", "load_frames"]

_KINDS = ("dataset", "gltf", "vertices", "motion")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("run", help="training run folder (or a checkpoint file)")
    parser.add_argument("--out", required=True, help="output folder for the viewer bundle")
    parser.add_argument("--animation", nargs="+", default=["dataset"], metavar=("KIND", "FILE"),
                        help="dataset (default), gltf FILE, vertices FILE (.npy, mesh-sequence .npz, "
                        "OBJ/PLY folder) or motion FILE")
    parser.add_argument("--model-dir", default=None,
                        help="motion: SMPL/FLAME model files (default: the run's, then $MESHSPLAT_MODEL_DIR)")
    parser.add_argument("--clip", default=None, help="glTF clip name (default the first)")
    parser.add_argument("--split", default=None, help="dataset: only the frames of this split")
    parser.add_argument("--dataset", default=None, help="dataset folder (default: the one in RUN/config.json)")
    parser.add_argument("--frames", type=int, default=None, help="keep at most N frames")
    parser.add_argument("--fps", type=float, default=25.0, help="playback (and glTF sampling) rate (default 25)")
    parser.add_argument("--title", default=None, help="page title (default: the run folder's name)")
    parser.add_argument("--background", choices=("white", "black"), default="white", help="initial background")
    parser.add_argument("--vertex-encoding", choices=("int16", "float32"), default="int16",
                        help="storage of the animated vertices (default int16, quantized per bundle)")
    parser.add_argument("--serve", action="store_true", help="serve the bundle on 127.0.0.1 after writing it")
    parser.add_argument("--port", type=int, default=8000, help="port for --serve (default 8000)")


def load_frames(avatar, args: argparse.Namespace, run_info=None) -> list:
    """Vertex frames [V,3] chosen by ``--animation`` (via meshsplat.animate helpers)."""
    import torch

    from meshsplat import animate

    kind, *rest = args.animation
    if kind not in _KINDS:
        raise MeshsplatError(f"--animation: expected one of {', '.join(_KINDS)}, got {kind!r}")
    if kind == "dataset":
        if rest:
            raise MeshsplatError("--animation dataset takes no file (use --dataset PATH)")
        from meshsplat.eval.run import open_run_dataset

        ds = open_run_dataset(run_info, args.dataset, check_masks=False)
        if args.split:
            frames, _ = animate.dataset_animation(avatar, ds, args.split)
        else:
            drv = ds.driver()
            n = drv.num_frames if args.frames is None else min(drv.num_frames, args.frames)
            frames = animate.sequence_animation(avatar, torch.stack([drv.vertices(i) for i in range(n)]).numpy())
    else:
        if len(rest) != 1:
            raise MeshsplatError(f"--animation {kind} needs exactly one FILE")
        if kind == "gltf":
            frames = animate.gltf_animation(avatar, rest[0], clip=args.clip, fps=args.fps,
                                            source_map=animate.run_source_map(run_info, args.dataset))
        elif kind == "motion":
            from meshsplat.eval.run import open_run_dataset

            ds = open_run_dataset(run_info, args.dataset, check_masks=False)
            mdir = args.model_dir or run_info.config.get("model_dir") or None
            frames = animate.motion_animation(avatar, ds, rest[0], mdir, max_frames=args.frames)
        else:
            frames = animate.sequence_animation(avatar, rest[0],
                                                source_map=animate.run_source_map(run_info, args.dataset))
    if args.frames is not None:
        if args.frames < 1:
            raise MeshsplatError(f"--frames: expected >= 1, got {args.frames}")
        frames = frames[: args.frames]
    return frames


def _serve(folder: Path, port: int) -> None:
    import functools
    import http.server

    handler = functools.partial(http.server.SimpleHTTPRequestHandler, directory=str(folder))
    try:
        server = http.server.ThreadingHTTPServer(("127.0.0.1", port), handler)
    except OSError as exc:
        raise MeshsplatError(f"--port: cannot listen on 127.0.0.1:{port} ({exc.strerror})") from None
    print(f"serving {folder} on http://127.0.0.1:{port}/index.html (Ctrl-C to stop)")
    try:
        server.serve_forever()
    finally:
        server.server_close()


def run(args: argparse.Namespace) -> int:
    from meshsplat.eval.run import load_run
    from meshsplat.viewer import write_viewer_bundle

    if args.fps <= 0:
        raise MeshsplatError(f"--fps: expected > 0, got {args.fps}")
    r = load_run(args.run, device="cpu")
    frames = load_frames(r.avatar, args, r)
    title = args.title or r.run_dir.resolve().name
    index = write_viewer_bundle(r.avatar, frames, Path(args.out), fps=args.fps, title=title,
                                vertex_encoding=args.vertex_encoding, background=args.background)
    size = sum(p.stat().st_size for p in index.parent.iterdir() if p.is_file())
    print(f"viewer: {index} ({len(frames)} frames, {r.avatar.num_gaussians} Gaussians, "
          f"{index.stat().st_size / 1e6:.1f} MB page, {size / 1e6:.1f} MB folder)")
    print(f"  open file://{index.resolve()}")
    if args.serve:
        _serve(index.parent, args.port)
    return 0
