"""Render a trained avatar in any animation to PNG frames and an MP4.

Animation (the same words as `meshsplat view` and ``meshsplat.animation.AnimationSource``):
  --animation dataset [--split NAME]      the capture's meshes (default); one split's with each frame's camera
  --animation gltf FILE [--clip NAME]     a glTF/GLB clip driving the avatar's mesh (any clip of the asset it
                                          was synthesized from), sampled at --fps for --seconds from --start
  --animation vertices FILE               a vertex sequence [T,V,3] (.npy), a mesh-sequence .npz or a folder
                                          of OBJ/PLY frames, in the canonical or the asset's order
  --animation blendshapes [FILE.npz|ict]  a blend-shape model (default: a head tracked by `meshsplat track`
                                          its capture's head_model.npz, else the bundled ICT head, as trained
                                          from `meshsplat synth ict`) driven by --weights W.json|W.npy [T,K], else a
                                          talking sequence of --frames (125) at --fps
  --animation motion FILE [--model-dir D] SMPL/SMPL-X motion .npz, IMavatar flame_params.json or a VHAP
                                          flame_param/ folder (avatars of SMPL/FLAME captures)
--frames N keeps the first N frames.

Camera (the same words as `meshsplat view` and the player page's camera): an orbit auto-framed on the
animation, or --camera page:FOLDER (a viewer page's initial camera, to compare a render with the page;
'page:FOLDER#view=...', quoted, the view the page shows now: its address or its "copy view"),
refined by --center X,Y,Z --azimuth DEG --elevation DEG --distance D --fov DEG --up X,Y,Z --front X,Y,Z,
with --orbit DEG turning it over the frames; or --camera dataset:<camera_id>. With --animation dataset
--split and no camera option each frame uses its own dataset camera. The orbit turns about the
capture's up (its cameras' mean up vector, snapped to a world axis) and starts at its front (azimuth 0:
+z in a +y-up world, else the side of the subject its first camera looks from).

Examples:
  meshsplat render runs/cesium --animation gltf CesiumMan.glb --orbit 360 --size 512x512 --out out/orbit
  meshsplat render runs/cesium --animation dataset --split test_clip --out out/test_clip
  meshsplat render runs/cesium --animation gltf CesiumMan.glb --camera page:out/viewer --out out/as_page
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from pathlib import Path
from typing import Any

from meshsplat import animate, camera
from meshsplat.animation import load_animation
from meshsplat.camera import Camera
from meshsplat.cli._guards import animation_bytes, check_memory, check_output_dir, check_range, render_bytes
from meshsplat.cli._options import (
    add_animation_options,
    add_camera_options,
    add_dataset_option,
    add_render_options,
    add_run_argument,
    animation_source,
    capture_up_front,
    orbit_request,
    render_options,
)
from meshsplat.cli.threads import add_threads_argument, apply_threads
from meshsplat.data.dataset import AvatarDataset
from meshsplat.errors import MeshsplatError
from meshsplat.run_folder import load_run

__all__ = ["add_arguments", "run", "render_cameras"]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_run_argument(parser, dataset=False)
    parser.add_argument("--out", required=True, help="output folder (frames/ and <name>.mp4)")
    add_animation_options(parser)
    add_dataset_option(parser)
    add_camera_options(parser, orbit_turn=True)
    add_render_options(parser, size=True)
    parser.add_argument("--name", default="animation", help="video file name (without .mp4)")
    parser.add_argument("--no-mp4", action="store_true", help="PNG frames only")
    parser.add_argument("--no-png", action="store_true", help="MP4 only")
    add_threads_argument(parser)


def render_cameras(
    args: argparse.Namespace,
    frames: list,
    frame_cams: list[Camera] | None,
    size: tuple[int, int] | None,
    up_front: Callable[[], tuple[Any, Any]],
    dataset: Callable[[], AvatarDataset],
) -> Camera | list[Camera]:
    """The cameras the flags describe for ``frames``: a dataset camera, each frame's own (a dataset split
    without camera flags), or the orbit of the page's camera language (``orbit_request``)."""
    req = orbit_request(args, *up_front())
    if req is None:
        return dataset().camera(args.camera.split(":", 1)[1], size)
    flags = (args.camera, args.center, args.distance, args.elevation, args.azimuth, args.fov, args.up, args.front)
    if frame_cams is not None and args.orbit is None and all(f is None for f in flags):
        return [c.resized(*size) for c in frame_cams] if size else frame_cams
    page_size = (int(req.pop("width", 512)), int(req.pop("height", 512)))
    w, h = size or page_size
    return camera.orbit_cameras(frames, w, h, orbit_deg=args.orbit or 0.0, **req)


def run(args: argparse.Namespace) -> int:
    if args.no_png and args.no_mp4:
        raise MeshsplatError("--no-png and --no-mp4 together leave nothing to write; drop one of them")
    if args.frames is not None and args.frames < 1:
        raise MeshsplatError(f"--frames: expected >= 1, got {args.frames}")
    opts = render_options(args)
    size = opts.size
    check_output_dir(args.out)
    apply_threads(args)
    r = load_run(args.run, device=opts.device, allow_older=args.allow_older_checkpoint)
    source = animation_source(args, r, "render")
    avatar = r.avatar
    ds = None
    w0, h0 = size or (512, 512)  # the estimate before the cameras are known (checked again below)

    def before_posing(n: int) -> None:
        """Frame limit and memory of ``n`` frames, before any is posed (a 200,000-frame motion)."""
        check_range("frames to render", n, "render frames")
        check_memory(
            f"rendering {n:,} frames of {avatar.mesh.num_vertices:,} vertices at {w0}x{h0}",
            render_bytes(w0, h0, n) + animation_bytes(n, avatar.mesh.num_vertices),
            "render fewer frames (--frames N) or lower --size",
        )

    def dataset():
        nonlocal ds
        if ds is None:
            ds = r.open_dataset(args.dataset, check_masks=False)
        return ds

    needs_ds = source.kind in ("dataset", "motion")
    anim = load_animation(
        source,
        avatar,
        dataset=dataset() if needs_ds else None,
        source_map=r.source_map(args.dataset),
        check=before_posing,
    )
    frames = anim.vertex_frames()
    cameras = render_cameras(args, frames, anim.cameras, size, lambda: capture_up_front(r, args.dataset, ds), dataset)
    check_range("frames to render", len(frames), "render frames")
    sizes = [(c.width, c.height) for c in (cameras if isinstance(cameras, list) else [cameras])]
    w, h = max(sizes, key=lambda s: s[0] * s[1])
    check_memory(
        f"rendering {len(frames)} frames at {w}x{h}",
        render_bytes(w, h, len(frames)) + animation_bytes(len(frames), avatar.mesh.num_vertices),
        "lower --size, or render fewer frames (--seconds, --fps, --frames)",
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
    print(f"rendered {res.num_frames} frames ({res.render_ms_mean:.1f} ms/frame) of {source.describe()} to {args.out}")
    if res.mp4 is not None:
        print(f"  video: {res.mp4}")
    if res.pngs:
        print(f"  frames: {res.pngs[0].parent}/ ({len(res.pngs)} PNG)")
    if res.error:
        print(f"  note: {res.error}")
    return 0
