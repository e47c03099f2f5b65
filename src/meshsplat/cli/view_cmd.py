"""Write a self-contained WebGL viewer (open index.html in a browser) animating a trained avatar.

Animation (default: the run's dataset meshes, all stored frames in order):
  --animation dataset [--split NAME]     the dataset's meshes (or those of one split)
  --animation gltf FILE [--clip NAME]    a glTF/GLB rig driving the avatar's mesh, LIVE: its skin,
                                         morph targets and clips ship in the page (clip picker,
                                         scrubbing, speed, morph sliders); --bake ships vertex
                                         frames sampled at --fps instead
  --animation vertices FILE              a vertex sequence [T,V,3] (.npy, mesh-sequence .npz, OBJ/PLY folder)
  --animation motion FILE                SMPL/SMPL-X motion .npz, FLAME flame_params.json or VHAP
                                         flame_param/ (avatars of SMPL/FLAME captures; baked to frames)
  --animation blendshapes [FILE.npz]     a blendshape face (default the bundled ICT FaceKit ARKit
                                         model) LIVE: one slider per expression, and a procedural
                                         talking sequence (--frames, default 125, at --fps) as a clip
--frames N keeps the first N frames. The page works from file://; --serve also serves the
folder on http://127.0.0.1:PORT until Ctrl-C.

Examples:
  meshsplat view runs/demo --out out/viewer
  meshsplat view runs/demo --animation gltf CesiumMan.glb --out out/viewer
  meshsplat view runs/demo --animation gltf CesiumMan.glb --bake --frames 60 --out out/viewer
"""

from __future__ import annotations

import argparse
import functools
import http.server
from pathlib import Path

import torch

from meshsplat import animate
from meshsplat.cli._guards import animation_bytes, check_memory, check_output_dir, check_range
from meshsplat.cli._options import (
    add_dataset_option,
    add_render_options,
    add_run_argument,
    capture_up_front,
    render_options,
)
from meshsplat.drivers import BlendshapeDriver
from meshsplat.errors import MeshsplatError
from meshsplat.gaussians import Avatar
from meshsplat.paths import resolve_input
from meshsplat.run_folder import LoadedRun, load_run
from meshsplat.viewer import write_viewer_bundle
from meshsplat.viewer.rig import avatar_driver

__all__ = ["add_arguments", "run", "load_frames"]

_KINDS = ("dataset", "gltf", "vertices", "blendshapes", "motion")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_run_argument(parser, dataset=False)
    parser.add_argument("--out", required=True, help="output folder for the viewer bundle")
    parser.add_argument(
        "--animation",
        nargs="+",
        default=["dataset"],
        metavar=("KIND", "FILE"),
        help="dataset (default), gltf FILE, vertices FILE (.npy, mesh-sequence .npz, OBJ/PLY "
        "folder), blendshapes [FILE.npz] or motion FILE",
    )
    parser.add_argument(
        "--motion",
        default=None,
        metavar="FILE",
        help="same as --animation motion FILE (SMPL/SMPL-X .npz, flame_params.json, flame_param/)",
    )
    parser.add_argument(
        "--model-dir",
        default=None,
        help="motion: SMPL/FLAME model files (default: the run's, then $MESHSPLAT_MODEL_DIR)",
    )
    parser.add_argument("--clip", default=None, help="glTF clip name (default the first)")
    parser.add_argument("--split", default=None, help="dataset: only the frames of this split")
    add_dataset_option(parser)
    parser.add_argument("--frames", type=int, default=None, help="keep at most N frames")
    parser.add_argument("--fps", type=float, default=25.0, help="playback (and glTF sampling) rate (default 25)")
    parser.add_argument("--title", default=None, help="page title (default: the run folder's name)")
    add_render_options(parser, device=False, backend=False, background=("white", "black"), progress=False)
    parser.add_argument(
        "--vertex-encoding",
        choices=("int16", "float32"),
        default="int16",
        help="storage of the animated vertices (default int16, quantized per bundle)",
    )
    parser.add_argument(
        "--bake", action="store_true", help="gltf / blendshapes: ship vertex frames (at --fps) instead of the live rig"
    )
    parser.add_argument("--serve", action="store_true", help="serve the bundle on 127.0.0.1 after writing it")
    parser.add_argument("--port", type=int, default=8000, help="port for --serve (default 8000)")


def _before_posing(avatar: Avatar):
    """The check of ``n`` frames before any is posed: the documented limit and the memory they take."""
    v = avatar.mesh.num_vertices

    def check(n: int) -> None:
        check_range("frames in the viewer", n, "view --frames")
        check_memory(
            f"a viewer of {n:,} frames of {v:,} vertices", animation_bytes(n, v), "keep fewer frames (--frames N)"
        )

    return check


def load_frames(avatar: Avatar, args: argparse.Namespace, run_info: LoadedRun) -> list:
    """Vertex frames [V,3] chosen by ``--animation`` (via meshsplat.animate helpers); the frame limit and the
    memory estimate are checked before the frames are posed."""
    kind, *rest = args.animation
    check = _before_posing(avatar)
    if kind not in _KINDS:
        raise MeshsplatError(f"--animation: expected one of {', '.join(_KINDS)}, got {kind!r}")
    if kind == "dataset":
        if rest:
            raise MeshsplatError("--animation dataset takes no file (use --dataset PATH)")
        ds = run_info.open_dataset(args.dataset, check_masks=False)
        if args.split:
            frames, _ = animate.dataset_animation(avatar, ds, args.split)
        else:
            drv = ds.driver()
            n = drv.num_frames if args.frames is None else min(drv.num_frames, args.frames)
            check(n)
            frames = animate.sequence_animation(avatar, torch.stack([drv.vertices(i) for i in range(n)]).numpy())
    elif kind == "blendshapes":
        drv = _blendshape_driver(avatar, rest, args)
        n = drv.num_frames if args.frames is None else min(drv.num_frames, args.frames)
        check(n)
        frames = [drv.vertices(i) for i in range(n)]
    else:
        if len(rest) != 1:
            raise MeshsplatError(f"--animation {kind} needs exactly one FILE")
        if kind == "gltf":
            frames = animate.gltf_animation(
                avatar, rest[0], clip=args.clip, fps=args.fps, source_map=run_info.source_map(args.dataset)
            )
        elif kind == "motion":
            ds = run_info.open_dataset(args.dataset, check_masks=False)
            mdir = run_info.model_dir(args.model_dir or None)
            frames = animate.motion_animation(avatar, ds, rest[0], mdir, max_frames=args.frames, check=check)
        else:
            frames = animate.sequence_animation(avatar, rest[0], source_map=run_info.source_map(args.dataset))
    if args.frames is not None:
        if args.frames < 1:
            raise MeshsplatError(f"--frames: expected >= 1, got {args.frames}")
        frames = frames[: args.frames]
    return frames


def _blendshape_driver(avatar, rest: list, args: argparse.Namespace):
    """BlendshapeDriver of FILE (default the bundled ICT FaceKit head) with a talking sequence."""
    if len(rest) > 1:
        raise MeshsplatError("--animation blendshapes takes at most one FILE.npz")
    drv = BlendshapeDriver.from_npz(rest[0] if rest else None)
    v = int(drv.neutral.shape[0])
    if v != avatar.mesh.num_vertices:
        raise MeshsplatError(
            f"--animation blendshapes: the model has {v} vertices, the avatar's mesh "
            f"{avatar.mesh.num_vertices}; use the blendshape model the avatar was trained on"
        )
    n = 125 if args.frames is None else args.frames
    if n < 1:
        raise MeshsplatError(f"--frames: expected >= 1, got {n}")
    drv.talking_sequence(n, args.fps)
    return drv


def _serve(folder: Path, port: int) -> None:
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
    check_range("--fps", args.fps, "view --fps")
    check_range("--frames", args.frames, "view --frames")  # also < 1, before any work
    if args.serve:
        check_range("--port", args.port, "view --port")
    check_output_dir(args.out)
    if args.motion is not None:
        if args.animation != ["dataset"]:
            raise MeshsplatError("--motion and --animation exclude each other")
        args.animation = ["motion", args.motion]
    opts = render_options(args)
    r = load_run(args.run, device="cpu", allow_older=args.allow_older_checkpoint)
    title = args.title or r.run_dir.resolve().name
    up, front = capture_up_front(r, args.dataset)
    camera = {"up": up, "front": front}  # the orbit turns about the capture's up, from its front
    kind, *rest = args.animation
    rig = frames = None
    if kind == "gltf" and not args.bake:
        if len(rest) != 1:
            raise MeshsplatError("--animation gltf needs exactly one FILE")
        glb = resolve_input(rest[0])
        if not glb.is_file():
            raise MeshsplatError(f"glTF file not found: {rest[0]} (check --animation gltf FILE)")
        rig = avatar_driver(r.avatar, glb, clip=args.clip, source_map=r.source_map(args.dataset))
        what = f"live glTF rig, {len(rig.clips)} clip(s), {sum(rig.morph_nodes().values())} morph target(s)"
    elif kind == "blendshapes" and not args.bake:
        rig = _blendshape_driver(r.avatar, rest, args)
        what = f"live blendshapes, {len(rig.names)} expressions, {rig.num_frames}-frame sequence"
    else:
        frames = load_frames(r.avatar, args, r)
        what = f"{len(frames)} frames"
    index = write_viewer_bundle(
        r.avatar,
        frames,
        Path(args.out),
        fps=args.fps,
        title=title,
        vertex_encoding=args.vertex_encoding,
        background=opts.background or "white",
        camera=camera,
        rig=rig,
    )
    size = sum(p.stat().st_size for p in index.parent.iterdir() if p.is_file())
    print(
        f"viewer: {index} ({what}, {r.avatar.num_gaussians} Gaussians, "
        f"{index.stat().st_size / 1e6:.1f} MB page, {size / 1e6:.1f} MB folder)"
    )
    print(f"  open file://{index.resolve()}")
    if args.serve:
        _serve(index.parent, args.port)
    return 0
