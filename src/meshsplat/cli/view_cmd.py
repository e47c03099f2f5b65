"""Write a self-contained WebGL viewer (open index.html in a browser) animating a trained avatar.

Animation (the same words as `meshsplat render` and ``meshsplat.animation.AnimationSource``):
  --animation dataset [--split NAME]      the capture's meshes (default: all stored frames in order)
  --animation gltf FILE [--clip NAME]     a glTF/GLB rig driving the avatar's mesh, LIVE: its skin, morph
                                          targets and clips ship in the page (clip picker, scrubbing, speed,
                                          morph sliders); --bake ships vertex frames sampled at --fps instead
  --animation vertices FILE               a vertex sequence [T,V,3] (.npy, mesh-sequence .npz, OBJ/PLY folder)
  --animation motion FILE                 SMPL/SMPL-X motion .npz, FLAME flame_params.json or VHAP
                                          flame_param/ (avatars of SMPL/FLAME captures; baked to frames)
  --animation blendshapes [FILE.npz|ict]  a blend-shape face (default: a head tracked by `meshsplat track`
                                          plays in its capture's head_model.npz, any other avatar in the
                                          bundled ICT FaceKit ARKit model, as `meshsplat synth ict`) LIVE: one
                                          slider per expression, and --weights [T,K] or a procedural
                                          talking sequence (--frames, default 125, at --fps) as a clip
--frames N keeps the first N frames.
Camera (the same words as `meshsplat render`): --camera page:FOLDER (another page's camera) or
dataset:<camera_id>, and --center X,Y,Z --azimuth --elevation --distance --fov --up --front.
The page works from file://; --serve also serves the folder on http://127.0.0.1:PORT until Ctrl-C.
--webcam (live blend-shape heads): a webcam button; the face in the camera drives the head (served pages only).

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

from meshsplat import camera
from meshsplat.animation import load_animation
from meshsplat.cli._guards import animation_bytes, check_memory, check_output_dir, check_range
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
from meshsplat.drivers import BlendshapeDriver, GltfDriver
from meshsplat.errors import MeshsplatError
from meshsplat.run_folder import load_run
from meshsplat.track.ict_head import load_ict_head
from meshsplat.viewer import write_viewer_bundle
from meshsplat.viewer.webcam import webcam_model

__all__ = ["add_arguments", "run"]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_run_argument(parser, dataset=False)
    parser.add_argument("--out", required=True, help="output folder for the viewer bundle")
    add_animation_options(parser)
    add_dataset_option(parser)
    add_camera_options(parser)
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
    parser.add_argument(
        "--webcam",
        nargs="?",
        const="",
        default=None,
        metavar="FOLDER",
        help="live blend-shape heads: add the webcam mode (the face in your camera drives the head, solved in "
        "the page; open it with --serve). Copies the face landmarker (npm @mediapipe/face_mesh, ~10 MB) beside "
        "the page from FOLDER (its package folder or an npm prefix; default $MESHSPLAT_NODE_TOOLS, .node-tools)",
    )
    parser.add_argument("--serve", action="store_true", help="serve the bundle on 127.0.0.1 after writing it")
    parser.add_argument("--port", type=int, default=8000, help="port for --serve (default 8000)")


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
    if args.serve:
        check_range("--port", args.port, "view --port")
    check_output_dir(args.out)
    opts = render_options(args)
    r = load_run(args.run, device="cpu", allow_older=args.allow_older_checkpoint)
    source = animation_source(args, r, "view")
    v = r.avatar.mesh.num_vertices

    def before_posing(n: int) -> None:
        """The documented limit and the memory of ``n`` frames, before any is posed."""
        check_range("frames in the viewer", n, "view --frames")
        check_memory(
            f"a viewer of {n:,} frames of {v:,} vertices", animation_bytes(n, v), "keep fewer frames (--frames N)"
        )

    title = args.title or r.run_dir.resolve().name
    needs_ds = source.kind in ("dataset", "motion") or (args.camera or "").startswith("dataset:")
    ds = r.open_dataset(args.dataset, check_masks=False) if needs_ds else None
    up, front = capture_up_front(r, args.dataset, ds)
    req = orbit_request(args, up, front)  # the orbit turns about the capture's up, from its front
    if req is None:
        assert ds is not None  # opened above for a dataset camera
        cam: camera.Camera | dict = ds.camera(args.camera.split(":", 1)[1])
    else:
        cam = req
    live = source.kind in ("gltf", "blendshapes") and not args.bake
    anim = load_animation(
        source, r.avatar, dataset=ds, source_map=r.source_map(args.dataset), live=live, check=before_posing
    )
    if isinstance(anim.driver, GltfDriver):
        rig = anim.driver
        what = f"live glTF rig, {len(rig.clips)} clip(s), {sum(rig.morph_nodes().values())} morph target(s)"
    elif isinstance(anim.driver, BlendshapeDriver):
        what = f"live blendshapes, {len(anim.driver.names)} expressions, {anim.driver.num_frames}-frame sequence"
    else:
        what = f"{len(anim.vertex_frames())} frames"
    webcam = None
    if args.webcam is not None:
        if not isinstance(anim.driver, (GltfDriver, BlendshapeDriver)):
            raise MeshsplatError(
                "--webcam: needs a live blend-shape head (--animation blendshapes without --bake, or a glTF rig "
                "with ARKit-named morph targets)"
            )
        webcam = webcam_model(load_ict_head())
    index = write_viewer_bundle(
        r.avatar,
        anim,
        Path(args.out),
        title=title,
        vertex_encoding=args.vertex_encoding,
        background=opts.background or "white",
        camera=cam,
        webcam=webcam,
        landmarker=args.webcam or None,
    )
    size = sum(p.stat().st_size for p in index.parent.iterdir() if p.is_file())
    print(
        f"viewer: {index} ({source.describe()}: {what}, {r.avatar.num_gaussians} Gaussians, "
        f"{index.stat().st_size / 1e6:.1f} MB page, {size / 1e6:.1f} MB folder)"
    )
    if webcam is not None:
        print("  webcam mode: serve the folder (--serve) and press webcam; the face is processed in the page only")
    print(f"  open file://{index.resolve()}")
    if args.serve:
        _serve(index.parent, args.port)
    return 0
