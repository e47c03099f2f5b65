"""Render a trained avatar in any animation to PNG frames and an MP4.

Drivers (pick one):
  --gltf FILE --clip NAME [--fps 25 --seconds S]   a glTF/GLB clip driving the avatar's mesh (any clip of the
                                                   asset it was synthesized from, smoothed/decimated or not)
  --vertices FILE                                  a vertex sequence [T,V,3] (.npy), a mesh-sequence .npz or a
                                                   folder of OBJ/PLY frames, in the canonical or the asset's order
  --blendshapes FILE.npz|ict --weights W.json|W.npy   blend-shape weights [T,K] (ICT head)
  --dataset-split NAME                             the driving meshes of a dataset split
  --motion FILE [--model-dir DIR]                  SMPL/SMPL-X motion .npz, IMavatar flame_params.json or a
                                                   VHAP flame_param/ folder (avatars of SMPL/FLAME captures)
Cameras: --camera dataset:<camera_id>, or an orbit auto-framed on the animation
(--orbit DEG total turn, --elevation DEG, --azimuth DEG, --distance D, --fov DEG); with
--dataset-split and no camera option each frame uses its own dataset camera. The orbit turns about
the capture's up (its cameras' mean up vector, snapped to a world axis) and starts at its front
(azimuth 0: +z in a +y-up world, else the side of the subject its first camera looks from).

Examples:
  meshsplat render runs/cesium --gltf CesiumMan.glb --orbit 360 --size 512x512 --out out/orbit
  meshsplat render runs/cesium --dataset-split test_clip --out out/test_clip
"""

from __future__ import annotations

import argparse
from pathlib import Path

from meshsplat import animate, camera
from meshsplat.camera import Camera
from meshsplat.cli._guards import animation_bytes, check_memory, check_output_dir, check_range, render_bytes
from meshsplat.cli._options import (
    add_dataset_option,
    add_render_options,
    add_run_argument,
    capture_up_front,
    render_options,
)
from meshsplat.cli.threads import add_threads_argument, apply_threads
from meshsplat.errors import MeshsplatError
from meshsplat.run_folder import load_run

__all__ = ["add_arguments", "run"]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_run_argument(parser, dataset=False)
    parser.add_argument("--out", required=True, help="output folder (frames/ and <name>.mp4)")
    drv = parser.add_mutually_exclusive_group(required=True)
    drv.add_argument("--gltf", help="glTF/GLB file whose mesh is the avatar's driving mesh")
    drv.add_argument(
        "--vertices",
        help="vertex sequence: .npy [T,V,3], mesh-sequence .npz or a folder of OBJ/PLY "
        "frames (canonical vertex order, or the synthesized asset's own order)",
    )
    drv.add_argument("--blendshapes", help="blend-shape model .npz (or 'ict' for the bundled ICT head)")
    drv.add_argument("--dataset-split", help="render the driving meshes of this dataset split")
    drv.add_argument(
        "--motion",
        help="SMPL/SMPL-X motion .npz (poses, trans), FLAME flame_params.json or a "
        "VHAP flame_param/ folder; the avatar keeps its own shape",
    )
    parser.add_argument(
        "--model-dir",
        default=None,
        help="--motion: SMPL/FLAME model files (default: the run's, then $MESHSPLAT_MODEL_DIR)",
    )
    parser.add_argument("--frames", type=int, default=None, help="--motion: render at most N frames")
    parser.add_argument("--clip", default=None, help="glTF clip name (default the first)")
    parser.add_argument("--fps", type=float, default=25.0, help="frame rate (default 25)")
    parser.add_argument("--seconds", type=float, default=None, help="glTF: seconds to render (default the clip)")
    parser.add_argument("--start", type=float, default=0.0, help="glTF: start time within the clip (s)")
    parser.add_argument("--weights", default=None, help="blend-shape weights [T,K] (.npy or .json)")
    add_dataset_option(parser)
    parser.add_argument("--camera", default=None, help="dataset:<camera_id>")
    parser.add_argument("--orbit", type=float, default=None, help="orbit camera: total turn in degrees (default 0)")
    parser.add_argument("--distance", type=float, default=None, help="orbit camera distance (default auto-framed)")
    parser.add_argument("--elevation", type=float, default=None, help="orbit camera elevation in degrees (default 10)")
    parser.add_argument(
        "--azimuth",
        type=float,
        default=0.0,
        help="orbit start azimuth in degrees (0 = from the capture's front: +z in a +y-up world)",
    )
    parser.add_argument("--fov", type=float, default=30.0, help="orbit camera vertical field of view (degrees)")
    add_render_options(parser, size=True)
    parser.add_argument("--name", default="animation", help="video file name (without .mp4)")
    parser.add_argument("--no-mp4", action="store_true", help="PNG frames only")
    parser.add_argument("--no-png", action="store_true", help="MP4 only")
    add_threads_argument(parser)


def run(args: argparse.Namespace) -> int:
    check_range("--fps", args.fps, "render --fps")
    check_range("--seconds", args.seconds, "render --seconds")
    check_range("--fov", args.fov, "render --fov")
    check_range("--elevation", args.elevation, "render --elevation")
    if args.distance is not None and not args.distance > 0:
        raise MeshsplatError(f"--distance: expected > 0, got {args.distance:g}")
    if args.seconds is not None:
        check_range("--fps x --seconds", args.fps * args.seconds, "render frames")
    if args.no_png and args.no_mp4:
        raise MeshsplatError("--no-png and --no-mp4 together leave nothing to write; drop one of them")
    if args.frames is not None and args.frames < 1:
        raise MeshsplatError(f"--frames: expected >= 1, got {args.frames}")
    opts = render_options(args)
    size = opts.size
    check_output_dir(args.out)
    apply_threads(args)
    r = load_run(args.run, device=opts.device, allow_older=args.allow_older_checkpoint)
    avatar = r.avatar
    ds = None

    def dataset():
        nonlocal ds
        if ds is None:
            ds = r.open_dataset(args.dataset, check_masks=False)
        return ds

    w0, h0 = size or (512, 512)  # the estimate before the cameras are known (a dataset camera: checked again below)

    def before_posing(n: int) -> None:
        """Frame limit and memory of ``n`` frames, before any is posed (a 200,000-frame motion)."""
        check_range("frames to render", n, "render frames")
        check_memory(
            f"rendering {n:,} frames of {avatar.mesh.num_vertices:,} vertices at {w0}x{h0}",
            render_bytes(w0, h0, n) + animation_bytes(n, avatar.mesh.num_vertices),
            "render fewer frames (--frames N) or lower --size",
        )

    frame_cams = None
    if args.gltf:
        frames = animate.gltf_animation(
            avatar, args.gltf, args.clip, args.fps, args.seconds, args.start, source_map=r.source_map(args.dataset)
        )
    elif args.vertices:
        frames = animate.sequence_animation(avatar, args.vertices, source_map=r.source_map(args.dataset))
    elif args.blendshapes:
        if not args.weights:
            raise MeshsplatError("--blendshapes needs --weights FILE (.npy or .json, [T,K])")
        model = None if args.blendshapes.lower() == "ict" else args.blendshapes
        frames = animate.blendshape_animation(avatar, model, args.weights, check=before_posing)
    elif args.motion:
        frames = animate.motion_animation(
            avatar,
            dataset(),
            args.motion,
            r.model_dir(args.model_dir or None),
            max_frames=args.frames,
            check=before_posing,
        )
    else:
        frames, frame_cams = animate.dataset_animation(avatar, dataset(), args.dataset_split)

    orbit_opts = args.orbit is not None or args.distance is not None or args.elevation is not None
    if args.camera:
        if not args.camera.startswith("dataset:"):
            raise MeshsplatError(f"--camera: expected dataset:<camera_id>, got {args.camera!r}")
        if orbit_opts:
            raise MeshsplatError("--camera and --orbit/--distance/--elevation exclude each other")
        cameras: Camera | list[Camera] = camera.dataset_camera(dataset(), args.camera.split(":", 1)[1], size)
    elif frame_cams is not None and not orbit_opts:
        cameras = [c.resized(*size) for c in frame_cams] if size else frame_cams
    else:
        w, h = size or (512, 512)
        up, front = capture_up_front(r, args.dataset, ds)
        cameras = camera.orbit_cameras(
            frames,
            w,
            h,
            orbit_deg=args.orbit or 0.0,
            azimuth_deg=args.azimuth,
            elevation_deg=10.0 if args.elevation is None else args.elevation,
            distance=args.distance,
            fov_deg=args.fov,
            up=up,
            front=front,
        )
    check_range("frames to render", len(frames), "render frames")
    sizes = [(c.width, c.height) for c in (cameras if isinstance(cameras, list) else [cameras])]
    w, h = max(sizes, key=lambda s: s[0] * s[1])
    check_memory(
        f"rendering {len(frames)} frames at {w}x{h}",
        render_bytes(w, h, len(frames)) + animation_bytes(len(frames), avatar.mesh.num_vertices),
        "lower --size, or render fewer frames (--seconds, --fps)",
    )
    res = animate.render_animation(
        avatar,
        frames,
        cameras,
        Path(args.out),
        fps=args.fps,
        background=opts.background or "white",
        name=args.name,
        write_pngs=not args.no_png,
        write_mp4=not args.no_mp4,
        backend=opts.backend,
        progress=opts.progress,
    )
    print(f"rendered {res.num_frames} frames ({res.render_ms_mean:.1f} ms/frame) to {args.out}")
    if res.mp4 is not None:
        print(f"  video: {res.mp4}")
    if res.pngs:
        print(f"  frames: {res.pngs[0].parent}/ ({len(res.pngs)} PNG)")
    if res.error:
        print(f"  note: {res.error}")
    return 0
