"""Convert a capture in any supported layout (PeopleSnapshot, IMavatar, INSTA, VHAP, native) to a native dataset.

The layout is detected unless --format is given. Images and masks are written as PNG (npy and alpha
masks are converted), meshes row for row, and the body/head model parameters are kept.
--downscale N writes the images and masks at 1/N of their size with K scaled to match
(docs/real-captures.md).
"""

from __future__ import annotations

import argparse

from meshsplat.cli._options import add_downscale_option, add_drop_bad_frames_option, add_reader_arguments
from meshsplat.data.convert import write_native
from meshsplat.data.dataset import AvatarDataset
from meshsplat.data.formats import FORMAT_NAMES, detect_format, open_capture, reader_options

__all__ = ["add_arguments", "run"]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("capture", metavar="DIR", help="capture folder")
    parser.add_argument("--out", required=True, help="native dataset folder to write")
    parser.add_argument("--format", choices=FORMAT_NAMES, default=None, help="capture layout (default: detect)")
    parser.add_argument(
        "--model-dir",
        default=None,
        help="folder with the smpl/, smplx/, flame/ model files (default $MESHSPLAT_MODEL_DIR)",
    )
    add_reader_arguments(parser)
    add_downscale_option(parser, "1 (as recorded)")
    parser.add_argument("--overwrite", action="store_true", help="write into a non-empty folder")
    add_drop_bad_frames_option(parser)


def run(args: argparse.Namespace) -> int:
    fmt = args.format or detect_format(args.capture)
    print(f"format: {fmt}{'' if args.format else ' (detected)'}")
    ds = open_capture(
        args.capture,
        format=fmt,
        model_dir=args.model_dir,
        drop_bad_frames=args.drop_bad_frames,
        downscale=1 if args.downscale is None else args.downscale,
        **reader_options(args.gender, args.shape),
    )
    if ds.meta.get("split_rule"):
        print(f"splits from {ds.meta['split_rule']}")
    print(
        f"{len(ds)} frames, {len(ds.camera_ids)} camera(s), splits: "
        + ", ".join(f"{s} {len(ds.split(s))}" for s in ds.split_names)
    )
    if ds.downscale != 1:
        print(f"downscale {ds.downscale:g}: images written at {_sizes(ds)}, K scaled to match")
    out = write_native(ds, args.out, overwrite=args.overwrite)
    driver = ds.driver_info
    print(f"native dataset written to {out}" + (f" (driver: {driver['type']})" if driver else ""))
    return 0


def _sizes(ds: AvatarDataset) -> str:
    """The distinct image sizes of the dataset's cameras, as read (``WxH, ...``)."""
    sizes = dict.fromkeys(f"{ds.camera(c).width}x{ds.camera(c).height}" for c in ds.camera_ids)
    return ", ".join(list(sizes)[:4]) + (" ..." if len(sizes) > 4 else "")
