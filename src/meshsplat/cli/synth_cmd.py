"""Render an animated asset or a body/head model into a ground-truth capture (images, masks, cameras, meshes).

SOURCE is a .glb/.gltf path (skin or morph animation), a mesh sequence (an .npz with faces [F,3] and
vertices [T,V,3], or a folder of OBJ/PLY frames; docs/bring-your-own-mesh.md), an ICT-layout .npz, a
bundled asset name (CesiumMan, RobotExpressive, RiggedSimple, ict) or
a parametric model: smpl / smplx (dancing the AIST++ clip) or flame (talking, nodding), read from
--model-dir or $MESHSPLAT_MODEL_DIR. --format writes the capture in another layout (e.g. peoplesnapshot
for smpl; imavatar, insta, vhap for flame) from a native dataset rendered first.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from meshsplat.cli._guards import check_memory, check_output_dir, check_range, synth_bytes
from meshsplat.cli.threads import add_threads_argument, apply_threads
from meshsplat.data.formats import FORMAT_NAMES
from meshsplat.errors import MeshsplatError
from meshsplat.synth import contact_sheet
from meshsplat.synth.capture import synth_capture
from meshsplat.synth.generate import RENDERERS, RIGS, SynthSpec
from meshsplat.synth.pbr import PbrSettings

__all__ = ["add_arguments", "run"]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "asset",
        metavar="SOURCE",
        help="glTF/GLB file, mesh-sequence .npz or OBJ/PLY frame folder, bundled asset name, or smpl/smplx/flame",
    )
    parser.add_argument("--out", required=True, help="output capture folder")
    parser.add_argument("--format", choices=FORMAT_NAMES, default="native", help="layout to write (default native)")
    parser.add_argument(
        "--model-dir",
        default=None,
        help="folder with the smpl/, smplx/, flame/ model files (default $MESHSPLAT_MODEL_DIR)",
    )
    parser.add_argument(
        "--gender", default="neutral", choices=("neutral", "male", "female"), help="body model gender (smpl/smplx)"
    )
    parser.add_argument(
        "--native-out",
        default=None,
        metavar="DIR",
        help="with --format other than native: also keep the native dataset here",
    )
    parser.add_argument(
        "--masks", choices=("png", "npy"), default=None, help="mask files for --format peoplesnapshot (default png)"
    )
    parser.add_argument(
        "--rig",
        choices=RIGS,
        default="monocular-turn",
        help="cameras: one fixed camera and a turning subject (monocular-turn, default), a camera circling "
        "the subject (orbit), or several fixed cameras (multiview)",
    )
    parser.add_argument("--frames", type=int, default=60, help="training time steps (per camera)")
    parser.add_argument("--resolution", type=int, default=256, help="square image size in pixels")
    parser.add_argument("--clip", default=None, help="training clip (default: the clip with the most motion)")
    parser.add_argument(
        "--test-clips",
        nargs="*",
        default=None,
        help="clips for the novel-pose test split (default: up to two other moving clips)",
    )
    parser.add_argument(
        "--up", choices=("y", "z"), default=None, help="the asset's up axis (default: the asset's own, glTF y; else y)"
    )
    parser.add_argument("--train-fraction", type=float, default=0.7, help="leading part of the clip used for training")
    parser.add_argument("--test-frames", type=int, default=None, help="frames per test split (default frames/4)")
    parser.add_argument("--test-views", type=int, default=2, help="held-out cameras")
    parser.add_argument("--views", type=int, default=8, help="cameras of the multiview rig")
    parser.add_argument(
        "--driver-smooth",
        type=int,
        default=0,
        metavar="ITERS",
        help="Taubin smoothing iterations applied to the stored driving mesh",
    )
    parser.add_argument(
        "--driver-decimate",
        type=float,
        default=None,
        metavar="RATIO",
        help="keep about RATIO of the driving mesh's vertices (vertex clustering)",
    )
    parser.add_argument(
        "--pose-noise",
        type=float,
        default=0.0,
        metavar="RADIANS",
        help="body/head models: tracking error, random joint rotations of this standard deviation in the stored poses",
    )
    parser.add_argument(
        "--renderer",
        choices=RENDERERS,
        default="lambert",
        help="lambert: fast rasterizer (default); pbr: path traced with shadows and gloss (needs meshsplat[pbr])",
    )
    parser.add_argument("--spp", type=int, default=32, help="--renderer pbr: samples per pixel (default 32)")
    parser.add_argument(
        "--roughness", type=float, default=0.45, help="--renderer pbr: roughness of the glossy lobe (default 0.45)"
    )
    parser.add_argument("--seed", type=int, default=0, help="seed of the path tracer and the pose noise (default 0)")
    parser.add_argument(
        "--light",
        default=None,
        metavar="X,Y,Z",
        help="world direction towards the light (y up; the rasterizer's directional light, the path tracer's key "
        "light; written in the meta as light_dir); default 0.35,0.75,0.55 (front, above, right)",
    )
    parser.add_argument(
        "--key", type=float, default=0.9, help="--renderer pbr: the key light's strength (default 0.9; 0: sky only)"
    )
    parser.add_argument("--supersample", type=int, default=None, help="anti-aliasing factor (default 2 up to 384 px)")
    parser.add_argument("--contact-sheet", default=None, metavar="PNG", help="also save a contact sheet (native only)")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing dataset")
    add_threads_argument(parser)


def run(args: argparse.Namespace) -> int:
    check_range("--resolution", args.resolution, "synth --resolution")
    check_range("--frames", args.frames, "synth --frames")
    check_range("--test-frames", args.test_frames, "synth --test-frames")
    check_range("--views", args.views, "synth --views")
    check_range("--test-views", args.test_views, "synth --test-views")
    check_range("--train-fraction", args.train_fraction, "synth --train-fraction")
    check_range("--driver-smooth", args.driver_smooth, "synth --driver-smooth")
    check_range("--driver-decimate", args.driver_decimate, "synth --driver-decimate")
    check_range("--supersample", args.supersample, "synth --supersample")
    check_range("--pose-noise", args.pose_noise, "synth --pose-noise")
    check_range("--spp", args.spp, "synth --spp")
    check_range("--roughness", args.roughness, "synth --roughness")
    check_range("--seed", args.seed, "synth --seed")
    if args.supersample and args.renderer == "pbr":
        raise MeshsplatError("--supersample applies to --renderer lambert; the path tracer antialiases with --spp")
    ss = args.supersample or (2 if args.resolution <= 384 else 1)
    check_range("--resolution x --supersample", args.resolution * ss, "synth resolution x supersample")
    check_memory(
        f"synth at {args.resolution} px with supersample {ss}",
        synth_bytes(args.resolution, ss),
        "lower --resolution or --supersample",
    )
    check_output_dir(args.out)
    if args.contact_sheet:
        check_output_dir(Path(args.contact_sheet).parent, "--contact-sheet")

    if args.masks is not None and args.format != "peoplesnapshot":
        raise MeshsplatError("--masks applies to --format peoplesnapshot only")
    if args.contact_sheet and args.format != "native":
        raise MeshsplatError("--contact-sheet needs --format native (or use --native-out and `meshsplat synth` output)")
    threads = apply_threads(args)
    write_options = {"masks": args.masks} if args.masks else {}
    spec = SynthSpec(
        rig=args.rig,
        frames=args.frames,
        resolution=args.resolution,
        clip=args.clip,
        test_clips=args.test_clips,
        train_fraction=args.train_fraction,
        test_frames=args.test_frames,
        test_views=args.test_views,
        views=args.views,
        driver_smooth=args.driver_smooth,
        driver_decimate=args.driver_decimate,
        supersample=args.supersample,
        model_dir=args.model_dir,
        gender=args.gender,
        up=args.up,
        renderer=args.renderer,
        pbr=PbrSettings(spp=args.spp, seed=args.seed, roughness=args.roughness, key=args.key),
        pose_noise=args.pose_noise,
        seed=args.seed,
        light_dir=_light_arg(args.light),
    )
    out = synth_capture(
        args.asset,
        args.out,
        format=args.format,
        native_dir=args.native_out,
        overwrite=args.overwrite,
        write_options=write_options,
        spec=spec,
        progress=True,
        threads=threads,
    )
    print(f"{args.format} capture written to {out}")
    if args.contact_sheet:
        print(f"contact sheet: {contact_sheet(out, args.contact_sheet)}")
    return 0


def _light_arg(text: str | None) -> list[float] | None:
    """``--light X,Y,Z`` as three numbers (None: the default light)."""
    if text is None:
        return None
    try:
        v = [float(x) for x in text.split(",")]
    except ValueError:
        v = []
    if len(v) != 3:
        raise MeshsplatError(f"--light: expected X,Y,Z (three numbers), got {text!r}")
    return v
