"""Options shared by the commands that read a run or render: declared once, parsed once.

``add_run_argument`` gives ``RUN`` (and ``--dataset``); ``add_render_options`` gives the rendering
flags (``--device --backend --background --size --no-progress``, each only where the command takes
it); ``render_options(args)`` turns them into the values the library takes. ``render`` and ``view`` say
an animation and a camera the same way: ``add_animation_options`` / ``animation_source`` (``--animation
KIND [FILE]`` and its options, an ``AnimationSource``) and ``add_camera_options`` / ``orbit_request``
(``--camera``, ``--center``, ``--azimuth``, ... : the player page's orbit description).
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from typing import Any

from meshsplat.animation import ANIMATION_KINDS, AnimationSource
from meshsplat.cli._guards import LIMITS, check_range
from meshsplat.data.dataset import DROP_FLAG, AvatarDataset
from meshsplat.errors import MeshsplatError
from meshsplat.run_folder import ALLOW_OLDER_FLAG, LoadedRun
from meshsplat.viewer.bundle import page_camera

__all__ = [
    "add_run_argument",
    "add_dataset_option",
    "add_drop_bad_frames_option",
    "capture_up_front",
    "add_reader_arguments",
    "add_render_options",
    "add_downscale_option",
    "render_options",
    "RenderOptions",
    "parse_size",
    "add_animation_options",
    "animation_source",
    "add_camera_options",
    "orbit_request",
]


def add_run_argument(parser: argparse.ArgumentParser, dataset: bool = True) -> None:
    """Positional ``run`` (a training run folder or a checkpoint file) and, with ``dataset``, ``--dataset``."""
    parser.add_argument("run", help="training run folder (or a checkpoint file)")
    parser.add_argument(
        ALLOW_OLDER_FLAG,
        action="store_true",
        help="when the run's newest checkpoint is unreadable, use its newest readable one (with a note "
        "naming the skipped file and the iteration used) instead of refusing",
    )
    if dataset:
        add_dataset_option(parser)


def add_reader_arguments(parser: argparse.ArgumentParser) -> None:
    """Capture reader options (``meshsplat.data.formats.reader_options``); a layout without one refuses it."""
    parser.add_argument(
        "--gender",
        choices=("neutral", "male", "female"),
        default=None,
        help="body model gender (PeopleSnapshot; default: the capture's config.json or its known subject)",
    )
    parser.add_argument(
        "--shape",
        choices=("per_split", "train"),
        default=None,
        help="PeopleSnapshot betas: per_split (default; each split posed with its own parameter file, the "
        "published protocol) or train (every frame with the train betas)",
    )


def add_dataset_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--dataset", default=None, help="dataset folder (default: the one in RUN/config.json)")


def capture_up_front(run: LoadedRun, dataset: str | None, ds: AvatarDataset | None = None) -> tuple[Any, Any]:
    """The capture's up and front (``dataset.up``, ``dataset.front``: what default and orbit cameras turn
    about and start from) for a run; +y up, +z front (the glTF convention) when no dataset is at hand."""
    if ds is None:
        try:
            run.dataset_path(dataset)
        except MeshsplatError:
            return (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)
        ds = run.open_dataset(dataset, check_masks=False)
    return ds.up, ds.front


def add_drop_bad_frames_option(parser: argparse.ArgumentParser) -> None:
    """``--drop-bad-frames``: leave out the few frames failing the camera check (else they are refused)."""
    parser.add_argument(
        DROP_FLAG,
        action="store_true",
        help="leave out the few frames whose camera does not see the subject (mesh behind the camera, "
        "outside the image or off the mask); without it they are listed and refused",
    )


def add_render_options(
    parser: argparse.ArgumentParser,
    *,
    device: str | bool | None = "auto",
    backend: bool = True,
    background: bool | tuple[str, ...] = True,
    size: bool = False,
    progress: bool = True,
) -> None:
    """Add the rendering flags a command takes.

    ``device``: the ``--device`` default (``"auto"``; ``None`` leaves the choice to the config), or
    False for none. ``background``: True for any colour, a tuple of names to restrict the choice (the
    viewer page only switches between white and black), False for none.
    """
    if size:
        parser.add_argument("--size", default=None, help="WxH (default: the dataset camera's size, or 512x512)")
    if background is True:
        parser.add_argument("--background", default="white", help="white, black or R,G,B in [0,1] (default white)")
    elif background:
        parser.add_argument(
            "--background",
            choices=tuple(background),
            default=background[0],
            help=f"initial background (default {background[0]})",
        )
    if device is not False:
        parser.add_argument("--device", default=device, help="cpu, cuda, cuda:1 or auto (default auto)")
    if backend:
        parser.add_argument(
            "--backend", default="auto", help="rasterizer backend: auto, torch, numba or gsplat (default auto)"
        )
    if progress:
        parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def add_downscale_option(parser: argparse.ArgumentParser, default_text: str) -> None:
    """``--downscale N``: read the capture at 1/N of its recorded size (default None: ``default_text``)."""
    parser.add_argument(
        "--downscale",
        type=float,
        default=None,
        metavar="N",
        help="read the images at 1/N of their size, K scaled to match (2: 1080x1080 -> 540x540; "
        f"sizes round(W/N)); default {default_text}",
    )


@dataclass(frozen=True)
class RenderOptions:
    """What ``add_render_options`` parsed; ``None`` where the command has no such flag or it was not given
    (the backend then is "auto")."""

    device: str | None
    backend: str  # "auto" where the command has no --backend
    background: str | None
    size: tuple[int, int] | None
    progress: bool


def parse_size(text: str) -> tuple[int, int]:
    """``"WxH"`` -> ``(W, H)`` within docs/limits.md's bounds."""
    try:
        w, h = (int(x) for x in text.lower().split("x"))
    except ValueError:
        raise MeshsplatError(f"--size: expected WxH such as 512x512, got {text!r}") from None
    lo, hi, _ = LIMITS["render --size"]
    if not (lo <= w <= hi and lo <= h <= hi):
        raise MeshsplatError(f"--size: expected {lo}..{hi} pixels per side, got {text!r} (see docs/limits.md)")
    return w, h


def render_options(args: argparse.Namespace) -> RenderOptions:
    """The rendering flags of ``args`` as library values (``--size`` checked and parsed)."""
    size = getattr(args, "size", None)
    return RenderOptions(
        device=getattr(args, "device", None),
        backend=getattr(args, "backend", "auto"),
        background=getattr(args, "background", None),
        size=parse_size(size) if size else None,
        progress=not getattr(args, "no_progress", False),
    )


# ---------------------------------------------------------------- one way to say an animation
def add_animation_options(parser: argparse.ArgumentParser) -> None:
    """``--animation KIND [FILE]`` and its options (``meshsplat.animation.AnimationSource``'s fields)."""
    parser.add_argument(
        "--animation",
        nargs="+",
        default=None,
        metavar=("KIND", "FILE"),
        help="what drives the avatar: dataset (default; --split NAME for one split with its cameras), "
        "gltf FILE (--clip), vertices FILE (.npy [T,V,3], mesh-sequence .npz, OBJ/PLY folder), "
        "blendshapes [FILE.npz|ict] (default: a tracked head's own head_model.npz, else the ICT head; --weights, "
        "else a talking sequence) or motion FILE "
        "(SMPL/SMPL-X .npz, flame_params.json, flame_param/)",
    )
    parser.add_argument("--clip", default=None, help="gltf: clip name (default the first)")
    parser.add_argument("--split", default=None, help="dataset: only this split's frames, each with its camera")
    parser.add_argument("--weights", default=None, help="blendshapes: weights [T,K] (.npy or .json)")
    parser.add_argument("--fps", type=float, default=25.0, help="frame rate (and glTF sampling rate; default 25)")
    parser.add_argument("--seconds", type=float, default=None, help="gltf: seconds to sample (default the clip)")
    parser.add_argument("--start", type=float, default=0.0, help="gltf: start time within the clip (s)")
    parser.add_argument(
        "--frames", type=int, default=None, help="keep at most N frames (blendshapes talking sequence: its length)"
    )
    parser.add_argument(
        "--model-dir",
        default=None,
        help="motion: SMPL/FLAME model files (default: the run's, then $MESHSPLAT_MODEL_DIR)",
    )


def animation_source(args: argparse.Namespace, run: LoadedRun, command: str) -> AnimationSource:
    """The ``AnimationSource`` the flags describe."""
    check_range("--fps", args.fps, f"{command} --fps")
    if args.frames is not None:
        check_range("--frames", args.frames, "render frames")
    if args.seconds is not None:
        check_range("--seconds", args.seconds, "render --seconds")
        check_range("--fps x --seconds", args.fps * args.seconds, "render frames")
    kind, *rest = list(args.animation) if args.animation else ["dataset"]
    if kind not in ANIMATION_KINDS:
        raise MeshsplatError(f"--animation: expected one of {', '.join(ANIMATION_KINDS)}, got {kind!r}")
    if len(rest) > 1:
        raise MeshsplatError(f"--animation {kind}: expected at most one FILE, got {len(rest)} ({' '.join(rest)})")
    model_dir = run.model_dir(args.model_dir or None) if kind == "motion" else args.model_dir
    file = rest[0] if rest else None
    if kind == "blendshapes" and file is None:
        file = run.head_model(args.dataset)  # a tracked head plays in its own fitted model; else the ICT head
    return AnimationSource(
        kind,
        file,
        clip=args.clip,
        split=args.split,
        weights=args.weights,
        fps=args.fps,
        seconds=args.seconds,
        start=args.start,
        frames=args.frames,
        model_dir=model_dir,
    )


# ---------------------------------------------------------------- one camera language
def _vector(flag: str, text: str | None) -> tuple[float, float, float] | None:
    if text is None:
        return None
    try:
        x, y, z = (float(t) for t in text.split(","))
    except ValueError:
        raise MeshsplatError(f"{flag}: expected X,Y,Z such as 0,1,0, got {text!r}") from None
    return x, y, z


def add_camera_options(parser: argparse.ArgumentParser, orbit_turn: bool = False) -> None:
    """The camera flags of ``render`` and ``view``: the player page's orbit description (``avatar.json``'s
    ``camera``), a page's camera (``--camera page:FOLDER``) or a dataset camera; ``orbit_turn`` adds
    ``--orbit DEG`` (a turn over the frames, render only)."""
    parser.add_argument(
        "--camera",
        default=None,
        help="dataset:<camera_id> (a capture camera) or page:FOLDER (the initial camera of a viewer page: "
        "its folder or avatar.json), page:FOLDER#view=... (the view the page showed: its address's #view= or "
        "its 'copy view'); the flags below override a page's values",
    )
    parser.add_argument(
        "--center", default=None, metavar="X,Y,Z", help="orbit centre (default the animation's box centre)"
    )
    parser.add_argument("--distance", type=float, default=None, help="orbit distance (default auto-framed)")
    parser.add_argument("--elevation", type=float, default=None, help="orbit elevation in degrees (default 10)")
    parser.add_argument(
        "--azimuth",
        type=float,
        default=None,
        help="orbit azimuth in degrees (default 0 = from the capture's front: +z in a +y-up world)",
    )
    parser.add_argument("--fov", type=float, default=None, help="vertical field of view in degrees (default 30)")
    parser.add_argument("--up", default=None, metavar="X,Y,Z", help="orbit axis (default the capture's up)")
    parser.add_argument(
        "--front", default=None, metavar="X,Y,Z", help="azimuth 0 direction (default the capture's front)"
    )
    if orbit_turn:
        parser.add_argument(
            "--orbit", type=float, default=None, help="total turn over the frames in degrees (default 0)"
        )


def orbit_request(args: argparse.Namespace, up: Any, front: Any) -> dict[str, Any] | None:
    """The orbit the camera flags describe, as ``meshsplat.camera.ORBIT_KEYS`` entries (a page's camera,
    then the flags; ``up``/``front`` the capture's where neither says), or None for a dataset camera."""
    spec = args.camera
    if spec is not None and not spec.startswith(("dataset:", "page:")):
        raise MeshsplatError(f"--camera: expected dataset:<camera_id> or page:FOLDER, got {spec!r}")
    flags = {
        "center": _vector("--center", args.center),
        "distance": args.distance,
        "azimuth_deg": args.azimuth,
        "elevation_deg": args.elevation,
        "fov_deg": args.fov,
        "up": _vector("--up", args.up),
        "front": _vector("--front", args.front),
    }
    given = {k: v for k, v in flags.items() if v is not None}
    if spec is not None and spec.startswith("dataset:"):
        if given or getattr(args, "orbit", None) is not None:
            raise MeshsplatError(
                "--camera dataset:<id> and the orbit flags (--center, --azimuth, ...) exclude each other"
            )
        return None
    if args.fov is not None:
        check_range("--fov", args.fov, "render --fov")
    if args.elevation is not None:
        check_range("--elevation", args.elevation, "render --elevation")
    if args.distance is not None and not args.distance > 0:
        raise MeshsplatError(f"--distance: expected > 0, got {args.distance:g}")
    out: dict[str, Any] = {"azimuth_deg": 0.0, "elevation_deg": 10.0, "fov_deg": 30.0, "up": up, "front": front}
    if spec is not None:
        out.update(page_camera(spec.split(":", 1)[1]))
    out.update(given)
    return out
