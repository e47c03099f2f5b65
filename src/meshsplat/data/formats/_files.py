"""The capture readers' kit of generic file helpers (every layout may use them; nothing here knows a model).

Reading: JSON with one-line errors, instant-ngp ``transforms*.json`` files (their names, merged frames),
the natural sort key of numbered file names, an npz read into a dict with its problem reported, image and
mask lookup, alpha decided per image, a fast vertices-only OBJ reader, the tail test split. Writing: an
output folder, JSON, coefficients fitted to a layout's width, the frames' pixels as uint8 PNG.
FLAME posing lives in ``_flame``.
"""

from __future__ import annotations

import json
import os
import re
from pathlib import Path

import numpy as np

from meshsplat.data.dataset import AvatarDataset
from meshsplat.data.manifest import Problems, inside_capture
from meshsplat.errors import MeshsplatError
from meshsplat.io.arrays import read_npz
from meshsplat.io.images import float_to_uint8, write_png
from meshsplat.io.json_file import read_json_object
from meshsplat.io.out_folder import empty_or_new_folder
from meshsplat.plausible import group_ids

__all__ = [
    "TRANSFORMS_FILE",
    "transforms_files",
    "natural_key",
    "npz_or_problem",
    "fit_out",
    "merge_transform_frames",
    "read_json",
    "prepare_out",
    "tail_split",
    "has_alpha",
    "alpha_frames",
    "find_file",
    "obj_vertices",
    "mask_choice",
    "frame_pixels",
    "write_json",
    "save_png",
    "MASK_MODES",
    "IMAGE_EXTS",
]

MASK_MODES = ("auto", "alpha", "folder", "none")
IMAGE_EXTS = (".png", ".jpg", ".jpeg")
DEFAULT_TEST_FRAMES = 350  # SplattingAvatar/INSTA: the last 350 frames are test frames
SMALL_TEST_FRACTION = 0.2  # captures with <= 350 frames: the last 20% are test frames
TRANSFORMS_FILE = re.compile(r"^transforms_([A-Za-z0-9_\-]+)\.json$")  # transforms_<split>.json
_DIGITS = re.compile(r"(\d+)")


def transforms_files(root: Path) -> dict[str, Path]:
    """``<split> -> root/transforms_<split>.json`` of the files present, in name order."""
    return {m.group(1): p for p in sorted(root.glob("transforms_*.json")) if (m := TRANSFORMS_FILE.match(p.name))}


def natural_key(s: str) -> list:
    """Sort key ordering numbered names as numbers (``img_2`` before ``img_10``)."""
    return [int(p) if p.isdigit() else p for p in _DIGITS.split(s)]


def npz_or_problem(path: Path, where: str, problems: Problems, what: str = "arrays") -> dict[str, np.ndarray] | None:
    """The arrays of ``path`` as a dict (``meshsplat.io.arrays.read_npz``: no pickles), or None with its
    one-line problem added to ``problems`` under ``where``."""
    try:
        return read_npz(path, what)
    except MeshsplatError as exc:
        problems.add(where, str(exc))
        return None


def fit_out(layout: str, name: str, a: np.ndarray, width: int) -> np.ndarray:
    """Coefficients ``a`` as the ``width`` a layout stores: zero-padded, or cut when the extra ones are zero
    (a one-line error naming the writer otherwise)."""
    a = np.asarray(a, np.float64).reshape(-1)
    if a.size > width:
        if np.any(a[width:] != 0):
            raise MeshsplatError(
                f"{layout} writer: {name} has {a.size} non-zero coefficients, the layout keeps {width}"
            )
        return a[:width]
    return np.concatenate([a, np.zeros(width - a.size)])


MASK_MODES = ("auto", "alpha", "folder", "none")

IMAGE_EXTS = (".png", ".jpg", ".jpeg")

DEFAULT_TEST_FRAMES = 350  # SplattingAvatar/INSTA: the last 350 frames are test frames

SMALL_TEST_FRACTION = 0.2  # captures with <= 350 frames: the last 20% are test frames


def merge_transform_frames(
    files, problems: Problems
) -> tuple[list[tuple[dict, dict, str]], dict[str, list[int]], list[dict]]:
    """Frames of instant-ngp style ``transforms*.json`` files ``[(split | None, path)]``, each frame once.

    Returns ``(frames, splits, tops)``: ``frames`` as ``(record, its file's top level, file name)`` in
    first-seen order (a frame is identified by its ``file_path``), ``splits`` name -> frame indices,
    ``tops`` the top-level objects of the files read. A file without a ``frames`` list is a problem.
    """
    frames: list[tuple[dict, dict, str]] = []
    index: dict[str, int] = {}
    splits: dict[str, list[int]] = {}
    tops: list[dict] = []
    for split, path in files:
        data = read_json(path)
        items = data.get("frames")
        if not isinstance(items, list):
            problems.add(path.name, "needs a 'frames' list")
            continue
        if split is not None:
            splits[split] = []
        for fr in items:
            key = str(fr.get("file_path")) if isinstance(fr, dict) else f"{path.name}#{len(frames)}"
            if key not in index:
                index[key] = len(frames)
                frames.append((fr, data, path.name))
            elif isinstance(fr, dict):
                first, first_top, first_name = frames[index[key]]
                differ = _disagreeing_keys(first, first_top, fr, data)
                if differ:
                    problems.add(
                        f"frame {index[key]} ({key!r})",
                        f"{path.name} disagrees with {first_name} on {', '.join(differ)}; the files must "
                        f"describe a frame alike (fix or remove one of them)",
                    )
            if split is not None:
                splits[split].append(index[key])
        tops.append(data)
    return frames, splits, tops


_CAMERA_TOP_KEYS = ("fl_x", "fl_y", "cx", "cy", "w", "h", "camera_angle_x", "camera_angle_y")


def _disagreeing_keys(a: dict, a_top: dict, b: dict, b_top: dict) -> list[str]:
    """Keys two files' records of one frame both give (the intrinsics also from their files' top level)
    with different values (numbers compared to 1e-6 relative)."""
    ea = {**{k: a_top[k] for k in _CAMERA_TOP_KEYS if k in a_top}, **a}
    eb = {**{k: b_top[k] for k in _CAMERA_TOP_KEYS if k in b_top}, **b}
    out = []
    for k in sorted(set(ea) & set(eb)):
        x, y = ea[k], eb[k]
        if x == y:
            continue
        try:
            same = np.allclose(np.asarray(x, np.float64), np.asarray(y, np.float64), rtol=1e-6, atol=1e-9)
        except (TypeError, ValueError):
            same = False
        if not same:
            out.append(k)
    return out


def read_json(path: Path) -> dict:
    """A JSON object from ``path`` (one-line MeshsplatError if missing or malformed)."""
    return read_json_object(path)


def write_json(path: Path, data: dict) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(data, indent=1))
    os.replace(tmp, path)


def prepare_out(out: Path | str, overwrite: bool, stale: tuple[str, ...] = ()) -> Path:
    """Create the output folder; with ``overwrite`` an existing one is reused after removing files
    matching ``stale`` (globs whose leftovers a reader would pick up, e.g. old split files)."""
    out = empty_or_new_folder(out, overwrite)
    out.mkdir(parents=True, exist_ok=True)
    for pattern in stale:
        for p in out.glob(pattern):
            if p.is_file():
                p.unlink()
    return out


def tail_split(n: int, test_frames: int | None) -> tuple[list[int], list[int]]:
    """``(train, test)`` frame positions: the last ``test_frames`` frames are test frames.

    Default (None): the last 350 when there are more than 350 frames, else the last 20% (at least one
    when there are two or more frames, none for a single frame).
    """
    if test_frames is None:
        k = DEFAULT_TEST_FRAMES if n > DEFAULT_TEST_FRAMES else (max(1, round(SMALL_TEST_FRACTION * n)) if n > 1 else 0)
    else:
        k = int(test_frames)
        if k < 0 or k >= n:
            raise MeshsplatError(f"test_frames: expected 0 <= test_frames < {n} (the number of frames), got {k}")
    return list(range(n - k)), list(range(n - k, n))


def has_alpha(path: Path) -> bool:
    """Whether an image file carries an alpha channel (PNG: colour type from the header)."""
    with open(path, "rb") as fh:
        head = fh.read(26)
    if head[:8] == b"\x89PNG\r\n\x1a\n" and len(head) >= 26:
        if head[25] in (4, 6):
            return True
        if head[25] != 3:
            return False
    from PIL import Image

    try:
        with Image.open(path) as im:
            return im.mode in ("RGBA", "LA", "PA") or "transparency" in im.info
    except (OSError, ValueError, Image.DecompressionBombError):
        return False


def _probe_alpha(root: Path, rel: str) -> bool | None:
    """Whether the image ``rel`` has an alpha channel; None when it is missing, unreadable or outside
    the capture (those are reported by the dataset's own checks)."""
    p = root / rel
    scratch = Problems(root)
    if inside_capture(root, rel, "image", "", scratch) is None or not p.is_file():
        return None
    if p.suffix.lower() in (".jpg", ".jpeg"):
        return False
    try:
        return has_alpha(p)
    except OSError:
        return None


def alpha_frames(root: Path, images: list[str], problems: Problems, required: bool = False) -> bool:
    """Whether the frames' images carry the masks in their alpha channel, decided per file: every
    image RGBA -> True, none -> False. Frames that disagree (some RGB among RGBA images) are one
    problem naming both groups, never a choice made from the first image; with ``required`` (mask mode
    'alpha') every image must have an alpha channel."""
    found = [_probe_alpha(root, rel) for rel in images]
    with_a = [i for i, a in enumerate(found) if a is True]
    without = [i for i, a in enumerate(found) if a is False]
    if (with_a and without) or (required and without):
        n = len(without)
        problems.add(
            "images",
            f"frame{'s' if n > 1 else ''} {group_ids(without)} {'are' if n > 1 else 'is'} RGB"
            + (f" but frames {group_ids(with_a)} are RGBA (alpha = mask)" if with_a else " (mask='alpha')")
            + "; the frames must agree: give every image an alpha channel, or none (masks from a mask "
            "folder), or choose mask='folder' or 'none'",
        )
    return bool(with_a) and (not without or required)


def whole_number(value: object, name: str) -> int:
    """A JSON field that counts (an image size, a timestep): an int, or a float without a fraction; else a
    ``ValueError`` naming it (``int()`` would turn ``640.7`` into 640 and ``true`` into 1)."""
    if isinstance(value, int) and not isinstance(value, bool):
        return value
    if isinstance(value, float) and value.is_integer():
        return int(value)
    raise ValueError(f"{name} must be a whole number, got {value!r:.40}")


def not_a_path(frame: dict, keys: tuple[str, ...]) -> str | None:
    """What is wrong with the first of a frame's optional path fields ``keys`` that holds something other than a
    string (absent or null is fine), or None."""
    for key in keys:
        value = frame.get(key)
        if value is not None and not isinstance(value, str):
            return f"{key!r} must be a path (a string), got {value!r:.40}"
    return None


def find_file(root: Path, rel: str, exts=IMAGE_EXTS) -> str | None:
    """``rel`` (relative to ``root``, POSIX) if it exists, else ``rel`` + one of ``exts``; None if absent."""
    rel = rel.replace("\\", "/")
    while rel.startswith("./"):
        rel = rel[2:]
    if (root / rel).is_file():
        return rel
    for e in exts:
        if (root / (rel + e)).is_file():
            return rel + e
    return None


def mask_choice(mode: str) -> str:
    if mode not in MASK_MODES:
        raise MeshsplatError(f"mask: expected one of {list(MASK_MODES)}, got {mode!r}")
    return mode


_V_LINE = re.compile(rb"^v[ \t]+([^\r\n]*)", re.M)


def obj_vertices(path: Path) -> tuple[np.ndarray, int]:
    """Vertex positions ``[V,3]`` float64 and the face count of an OBJ file, reading only its ``v`` lines
    and counting its ``f`` lines (fast path for thousands of same-topology frames: ~6 ms for 5023 vertices)."""
    data = path.read_bytes()
    vlines = _V_LINE.findall(data)
    nfaces = data.count(b"\nf ") + data.startswith(b"f ")
    if not vlines:
        raise MeshsplatError(f"{path}: no vertices")
    try:
        arr = np.array(b" ".join(vlines).split(), dtype=np.float64)
        if arr.size == 3 * len(vlines):
            return arr.reshape(-1, 3), nfaces
        # some lines carry colours (v x y z r g b): take the first three numbers of each line
        return np.array([ln.split()[:3] for ln in vlines], dtype=np.float64), nfaces
    except ValueError:
        raise MeshsplatError(f"{path}: malformed vertex line") from None


def frame_pixels(dataset: AvatarDataset, i: int) -> tuple[np.ndarray, np.ndarray | None]:
    """Frame ``i``'s image ``[H,W,3]`` and mask ``[H,W]`` (or None) as uint8, exactly as stored."""
    fr = dataset[i]
    rgb = float_to_uint8(fr.image)
    mask = None
    if fr.mask is not None:
        mask = float_to_uint8(fr.mask[..., 0])
    return rgb, mask


def save_png(path: Path, img: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    write_png(path, img)
