"""Options shared by the commands that read a run or render: declared once, parsed once.

``add_run_argument`` gives ``RUN`` (and ``--dataset``); ``add_render_options`` gives the rendering
flags (``--device --backend --background --size --no-progress``, each only where the command takes
it); ``render_options(args)`` turns them into the values the library takes.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from typing import Any

from meshsplat.cli._guards import LIMITS
from meshsplat.data.dataset import DROP_FLAG, AvatarDataset
from meshsplat.errors import MeshsplatError
from meshsplat.run_folder import ALLOW_OLDER_FLAG, LoadedRun

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
