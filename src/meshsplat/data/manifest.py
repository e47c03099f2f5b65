"""Validating a manifest-shaped description of a capture and opening it as an :class:`AvatarDataset`.

The one validation path of every reader (``build_dataset``; ``open_dataset`` for the native layout): the
containment rule for a capture's paths (``inside_capture``), one way to report problems (``Problems``:
grouped, the first line self-sufficient), camera, frame-file, mesh and split checks, plausible ranges
(``meshsplat.plausible``) and the cameras check at the door (``data.camera_check``).
"""

from __future__ import annotations

import json
import os
import re
import warnings
from pathlib import Path
from typing import cast

import numpy as np

from meshsplat.data.camera_check import check_cameras, group_ids
from meshsplat.data.dataset import DROP_FLAG, MASK_KINDS, AvatarDataset, _read_npy_mask
from meshsplat.data.writer import FORMAT_NAME, FORMAT_VERSION
from meshsplat.errors import MeshsplatError, MeshsplatWarning
from meshsplat.io.arrays import array_error_text, read_npy, read_npz
from meshsplat.io.images import image_size, read_image, read_mask
from meshsplat.plausible import focal_problem, parameter_problems

__all__ = ["open_dataset", "build_dataset", "Problems", "inside_capture", "outside_allowed", "ALLOW_OUTSIDE_ENV"]

ALLOW_OUTSIDE_ENV = "MESHSPLAT_ALLOW_OUTSIDE_FILES"  # "1": manifest paths may leave the dataset folder


def _is_int(x) -> bool:
    return isinstance(x, (int, np.integer)) and not isinstance(x, bool)


def _is_number(x) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool)


def _type_name(x) -> str:
    return {
        dict: "an object",
        list: "a list",
        str: "a string",
        bool: "a boolean",
        type(None): "null",
        int: "a number",
        float: "a number",
    }.get(type(x), type(x).__name__)


def outside_allowed(allow_outside: bool | None = None) -> bool:
    """``allow_outside`` if given, else whether ``MESHSPLAT_ALLOW_OUTSIDE_FILES=1`` is set."""
    return os.environ.get(ALLOW_OUTSIDE_ENV, "") == "1" if allow_outside is None else bool(allow_outside)


def inside_capture(
    root: Path, value: object, what: str, where: str, problems: Problems, allow_outside: bool | None = None
) -> str | None:
    """The one containment rule of every reader: ``value`` (a path from the capture's own files, relative
    to ``root``) must name a file inside the capture folder, symlinks resolved (a link inside the folder
    that points out of it is outside). Returns the path as given, or None with the reason in
    ``problems``. ``allow_outside`` (default: ``MESHSPLAT_ALLOW_OUTSIDE_FILES=1``) lifts the rule."""
    if not isinstance(value, str) or not value:
        problems.add(where, f"{what} must be a file path (a string), got {_type_name(value)}")
        return None
    if outside_allowed(allow_outside):
        return value
    norm = os.path.normpath(value.replace("\\", "/"))
    outside = os.path.isabs(norm) or norm == ".." or norm.startswith(".." + os.sep)
    if not outside:
        try:
            base = Path(root).resolve()
            outside = not (base / norm).resolve().is_relative_to(base)
        except (OSError, RuntimeError):  # a symlink loop: not a file inside the folder either
            outside = True
    if outside:
        problems.add(
            where,
            f"{what} {value!r} lies outside the dataset folder; copy it into the folder, "
            f"or set {ALLOW_OUTSIDE_ENV}=1 to allow it",
        )
        return None
    return value


_NUMBERED = re.compile(r"^(frame|timestep|camera|mesh) '?(\d+)\b'?")  # camera ids may be quoted

_DIGITS = re.compile(r"\d+")


def _key(where: str, what: str) -> tuple[str, str]:
    """Problems alike: on the same kind of item (frame, timestep, ...), equal but for their numbers."""
    m = _NUMBERED.match(where)
    return (m.group(1) if m else where, _DIGITS.sub("#", what))


class Problems:
    """Collects every problem of a folder; ``raise_if_any`` ends them in one MeshsplatError.

    The one way readers report problems. The message is grouped: the same problem on many frames (or
    timesteps, cameras, meshes), differing only in numbers such as the frame's own file name, is one line
    (``frames 3-17: mask file masks/0003.png is missing (shown for frame 3; alike for the other 14)``); the first line
    names the folder, the count and the first problem, so it reads on its own; at most
    ``MAX_LISTED`` lines follow, then how many more."""

    MAX_LISTED = 8  # lines after the first
    GROUP_FROM = 4  # the same problem on this many frames (or more) is one line; fewer are listed

    def __init__(self, root: Path) -> None:
        self.root = root
        self.items: list[str] = []
        self._parts: list[tuple[str, str]] = []

    def add(self, where: str, what: str) -> None:
        self.items.append(f"{where}: {what}" if where else what)
        self._parts.append((where, what))

    def lines(self) -> list[str]:
        """The problems grouped: one line per distinct problem, with the frames (etc.) it concerns."""
        groups: dict[tuple[str, str], tuple[str, str, list[int]]] = {}
        order: list[tuple[str, str]] = []
        for where, what in self._parts:
            m = _NUMBERED.match(where)
            if m is None:
                key = (where, what)
                if key not in groups:
                    groups[key] = (where, what, [])
                    order.append(key)
                continue
            key = _key(where, what)
            if key not in groups:
                groups[key] = (where, what, [])
                order.append(key)
            groups[key][2].append(int(m.group(2)))
        out = []
        for key in order:
            where, what, ids = groups[key]
            if len(set(ids)) < self.GROUP_FROM:  # a few: each as it is
                out += [f"{w}: {x}" for w, x in self._parts if _NUMBERED.match(w) and _key(w, x) == key] or [
                    f"{where}: {what}" if where else what
                ]
                continue
            alike = (
                "" if _DIGITS.search(what) is None else f" (shown for {where}; alike for the other {len(set(ids)) - 1})"
            )
            out.append(f"{key[0]}s {group_ids(ids)}: {what}{alike}")
        return out

    def raise_if_any(self) -> None:
        if self.items:
            lines = self.lines()
            n = len(self.items)
            head = f"invalid dataset {self.root} ({n} problem{'s' if n > 1 else ''}): {lines[0]}"
            rest = lines[1 : 1 + self.MAX_LISTED]
            more = len(lines) - 1 - len(rest)
            msg = head + "".join(f"\n  - {ln}" for ln in rest) + (f"\n  - ... and {more} more" if more else "")
            raise MeshsplatError(msg)


def _unscaled_hint(K: np.ndarray, w: int, h: int) -> str:
    """When ``K``'s principal point is the centre of an image larger than ``w x h`` by one factor: say that K
    looks written for that image and was not scaled with the images ("" otherwise)."""
    sx, sy = 2 * float(K[0, 2]) / w, 2 * float(K[1, 2]) / h
    if min(sx, sy) < 1.2 or abs(sx / sy - 1) > 0.1:
        return ""
    s = (sx + sy) / 2
    return (
        f"; K looks written for a {2 * K[0, 2]:.0f}x{2 * K[1, 2]:.0f} image ({s:.2g} times larger): it was not "
        f"scaled with the images, multiply its first two rows by {1 / s:.2g} (or give the full-size images)"
    )


def _check_camera(cid: str, cam: dict, problems: Problems) -> tuple[np.ndarray, np.ndarray] | None:
    where = f"camera {cid!r}"
    if not isinstance(cam, dict):
        problems.add(where, f"must be an object with K, viewmat, width, height, got {_type_name(cam)}")
        return None
    if not all(_is_int(cam.get(k)) for k in ("width", "height")):
        problems.add(where, f"width and height must be integers, got {cam.get('width')!r} and {cam.get('height')!r}")
        return None
    try:
        K = np.asarray(cam["K"], np.float64)
        vm = np.asarray(cam["viewmat"], np.float64)
        w, h = int(cam["width"]), int(cam["height"])
    except (KeyError, TypeError, ValueError) as exc:
        problems.add(where, f"needs K [3,3], viewmat [4,4], width, height ({exc})")
        return None
    ok = True
    if K.shape != (3, 3) or not np.isfinite(K).all():
        problems.add(where, f"K must be a finite 3x3 matrix, got shape {list(K.shape)}")
        return None
    if vm.shape != (4, 4) or not np.isfinite(vm).all():
        problems.add(where, f"viewmat must be a finite 4x4 matrix, got shape {list(vm.shape)}")
        return None
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        problems.add(where, f"non-positive focal length (fx={K[0, 0]:g}, fy={K[1, 1]:g})")
        ok = False
    elif w > 0 and h > 0 and (why := focal_problem(K, w, h)) is not None:
        problems.add(where, why)
        ok = False
    if not np.allclose(K[2], [0, 0, 1], atol=1e-6):
        problems.add(where, f"K last row must be [0, 0, 1], got {K[2].tolist()}")
        ok = False
    if w <= 0 or h <= 0:
        problems.add(where, f"non-positive image size {w}x{h}")
        ok = False
    elif not (0 < K[0, 2] < w and 0 < K[1, 2] < h):
        problems.add(
            where,
            f"principal point ({K[0, 2]:g}, {K[1, 2]:g}) lies outside the {w}x{h} image" + _unscaled_hint(K, w, h),
        )
        ok = False
    R = vm[:3, :3]
    if not np.allclose(vm[3], [0, 0, 0, 1], atol=1e-6):
        problems.add(where, f"viewmat last row must be [0, 0, 0, 1], got {vm[3].tolist()}")
        ok = False
    # a rotation's entries lie in [-1, 1]: larger ones are refused before squaring them (1e200 would overflow)
    if np.abs(R).max() > 1 + 1e-4 or not np.allclose(R @ R.T, np.eye(3), atol=1e-4) or np.linalg.det(R) < 0:
        problems.add(where, "viewmat rotation is not a rotation matrix (R R^T != I or det(R) != +1)")
        ok = False
    return (K, vm) if ok else None


def _load_canonical(root: Path, rel: str | None, problems: Problems):
    if rel is None:
        return None, None
    p = root / rel
    if not p.is_file():
        problems.add(rel, "canonical mesh file is missing")
        return None, None
    try:
        if p.suffix == ".obj":
            import trimesh

            m = cast("trimesh.Trimesh", trimesh.load(p, process=False, force="mesh"))
            v, f = np.asarray(m.vertices), np.asarray(m.faces)
        else:
            z = read_npz(p, "canonical mesh")
            missing = [k for k in ("vertices", "faces") if k not in z]
            if missing:
                problems.add(rel, f"canonical mesh lacks {missing} (found {sorted(z)})")
                return None, None
            v, f = z["vertices"], z["faces"]
    except MeshsplatError as exc:
        problems.add(rel, str(exc))
        return None, None
    except Exception as exc:  # noqa: BLE001 - any unreadable file is one reported problem
        problems.add(rel, f"cannot read canonical mesh ({array_error_text(exc, 'mesh file')})")
        return None, None
    if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3:
        problems.add(rel, f"expected vertices [V,3] and faces [F,3], got {list(v.shape)} and {list(f.shape)}")
        return None, None
    if not np.issubdtype(f.dtype, np.integer):
        problems.add(rel, f"faces must be integers, got {f.dtype} (store them as int32)")
        return None, None
    if not np.issubdtype(v.dtype, np.floating) and not np.issubdtype(v.dtype, np.integer):
        problems.add(rel, f"vertices must be numbers, got {v.dtype}")
        return None, None
    if len(v) == 0 or len(f) == 0:
        problems.add(rel, f"canonical mesh is empty ({len(v)} vertices, {len(f)} faces)")
        return None, None
    if not np.isfinite(v).all():
        problems.add(rel, f"canonical vertices contain {int((~np.isfinite(v)).sum())} NaN/Inf values")
    elif float(np.ptp(v, axis=0).max()) <= 0:
        problems.add(rel, "canonical mesh is a single point (all vertices equal)")
    if f.min() < 0 or f.max() >= len(v):
        problems.add(rel, f"face indices out of range [0, {len(v)})")
    else:
        e1, e2 = v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]
        if np.isfinite(v).all() and not (np.linalg.norm(np.cross(e1, e2), axis=1) > 0).any():
            problems.add(rel, f"all {len(f)} faces of the canonical mesh have zero area")
    return v, f


def open_dataset(
    path: Path | str,
    check_masks: bool = True,
    cache_size: int = 8,
    allow_outside: bool | None = None,
    drop_bad_frames: bool = False,
    downscale: float = 1,
) -> AvatarDataset:
    """Open and validate a dataset folder (or its ``manifest.json``).

    Checks the JSON type of every manifest field, files, PNG sizes (headers only) against the
    cameras, principal points, camera rotations and focal lengths, vertex counts and finiteness,
    a non-degenerate integer-faced canonical mesh, split indices and (when ``check_masks``) that no
    mask is empty. Paths must stay inside the folder unless ``allow_outside`` (default: the
    ``MESHSPLAT_ALLOW_OUTSIDE_FILES=1`` environment variable). All problems are reported in one
    MeshsplatError. The cameras are checked against the meshes and masks (``build_dataset``;
    ``drop_bad_frames`` leaves out the few frames that fail). ``downscale``: read at ``1 / downscale`` of the recorded size
    (:meth:`AvatarDataset.set_downscale`).
    """
    allow_outside = outside_allowed(allow_outside)
    root = Path(path)
    if root.is_file() and root.name == "manifest.json":
        root = root.parent
    if root.is_file():
        raise MeshsplatError(f"{root} is a file; expected a dataset folder (holding manifest.json)")
    if not root.is_dir():
        raise MeshsplatError(f"dataset folder not found: {root}")
    mpath = root / "manifest.json"
    if not mpath.is_file():
        raise MeshsplatError(f"{root}: no manifest.json (not a meshsplat dataset)")
    try:
        manifest = json.loads(mpath.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise MeshsplatError(f"{mpath}: invalid JSON ({exc})") from None
    except RecursionError:
        raise MeshsplatError(f"{mpath}: nested too deeply to be a dataset manifest") from None
    if not isinstance(manifest, dict) or manifest.get("format") != FORMAT_NAME:
        raise MeshsplatError(f"{mpath}: 'format' must be {FORMAT_NAME!r}")
    if not _is_int(manifest.get("version")) or manifest.get("version") != FORMAT_VERSION:
        raise MeshsplatError(
            f"{mpath}: unsupported format version {manifest.get('version')!r} (this reader: {FORMAT_VERSION})"
        )
    for key in ("canonical", "vertices", "cameras", "frames"):
        if key not in manifest:
            raise MeshsplatError(f"{mpath}: missing key {key!r}")
    frames = manifest["frames"]
    if not isinstance(frames, list) or not frames:
        raise MeshsplatError(f"{mpath}: 'frames' must be a non-empty list, got {_type_name(frames)}")

    problems = Problems(root)
    rel_canonical = inside_capture(root, manifest["canonical"], "canonical", "manifest", problems, allow_outside)
    rel_vertices = inside_capture(root, manifest["vertices"], "vertices", "manifest", problems, allow_outside)
    canonical, faces = _load_canonical(root, rel_canonical, problems)
    verts = None
    vpath = root / rel_vertices if rel_vertices is not None else None
    if rel_vertices is None or vpath is None:
        pass
    elif not vpath.is_file():
        problems.add(rel_vertices, "posed vertices file is missing")
    else:
        try:
            verts = read_npy(vpath, "posed vertices", mmap=True)
        except MeshsplatError as exc:
            problems.add(rel_vertices, str(exc))
        if verts is not None and not isinstance(verts, np.ndarray):
            problems.add(rel_vertices, "expected one .npy array [T,V,3]")
            verts = None
        if verts is not None and (verts.ndim != 3 or verts.shape[2] != 3 or verts.dtype.kind not in "fiu"):
            problems.add(rel_vertices, f"expected a number array [T,V,3], got {verts.dtype} {list(verts.shape)}")
            verts = None
        if verts is not None and canonical is not None and verts.shape[1] != canonical.shape[0]:
            problems.add(
                rel_vertices,
                f"vertex count mismatch: {verts.shape[1]} posed vertices per "
                f"frame but the canonical mesh has {canonical.shape[0]}",
            )
    driver_params = None
    if manifest.get("driver") is not None:
        driver_params = _load_driver_params(root, manifest["driver"], problems, allow_outside)
    return build_dataset(
        root,
        manifest,
        canonical,
        faces,
        verts,
        problems,
        check_masks=check_masks,
        cache_size=cache_size,
        driver_params=driver_params,
        allow_outside=allow_outside,
        drop_bad_frames=drop_bad_frames,
    ).set_downscale(downscale)


def _load_driver_params(root: Path, driver, problems: Problems, allow_outside: bool) -> dict[str, np.ndarray] | None:
    if not isinstance(driver, dict) or not isinstance(driver.get("type"), str):
        problems.add("manifest 'driver'", "must be an object with 'type' and 'params' (file name)")
        return None
    rel = inside_capture(root, driver.get("params"), "driver params", "manifest 'driver'", problems, allow_outside)
    if rel is None:
        return None
    try:
        params = read_npz(root / rel, "driver parameters")
    except MeshsplatError as exc:
        problems.add(rel, str(exc))
        return None
    for line in parameter_problems(params):
        problems.add(rel, line)
    return params


def build_dataset(
    root: Path,
    manifest: dict,
    canonical: np.ndarray | None,
    faces: np.ndarray | None,
    verts: np.ndarray | None,
    problems: Problems | None = None,
    check_masks: bool = True,
    cache_size: int = 8,
    driver_params: dict | None = None,
    format_name: str = "native",
    allow_outside: bool | None = None,
    drop_bad_frames: bool = False,
) -> AvatarDataset:
    """Validate a manifest-shaped description (files relative to ``root``) and open it lazily.

    The one validation path of every reader: ``manifest`` has ``cameras`` (id -> K, viewmat, width,
    height), ``frames`` (records with ``image``, ``camera``, ``mesh``, optional ``mask``/``mask_kind``),
    ``splits`` and ``meta``; ``canonical [V,3]``, ``faces [F,3]``, ``verts [T,V,3]`` are arrays (or
    None when they failed to load, with the reason already in ``problems``). Every path must stay inside
    ``root`` (:func:`inside_capture`, symlinks resolved) unless ``allow_outside`` (default:
    ``MESHSPLAT_ALLOW_OUTSIDE_FILES=1``), whatever the layout.
    All problems end in one MeshsplatError.

    Then the cameras are checked at the door (``data.camera_check``; the masks only with ``check_masks``): a camera that does not see the
    subject on nearly all its frames is refused in one line naming the likely convention mix-up; a few
    failing frames are refused in one line listing them, or left out with ``drop_bad_frames`` (their
    names in ``meta["dropped_frames"]``, splits renumbered).
    """
    problems = problems or Problems(root)
    allow_outside = outside_allowed(allow_outside)
    frames = manifest["frames"]
    vname = str(manifest.get("vertices", "vertices"))
    if verts is not None and (verts.ndim != 3 or verts.shape[2] != 3):
        problems.add(vname, f"expected shape [T,V,3], got {list(verts.shape)}")
        verts = None
    if verts is not None and canonical is not None and verts.shape[1] != canonical.shape[0]:
        problems.add(
            vname,
            f"vertex count mismatch: {verts.shape[1]} posed vertices per "
            f"frame but the canonical mesh has {canonical.shape[0]}",
        )
    bad_meshes: dict[int, int] = {}
    if verts is not None:
        for s in range(0, verts.shape[0], 256):
            nonfinite = (~np.isfinite(np.asarray(verts[s : s + 256]))).sum(axis=(1, 2))
            for j in np.nonzero(nonfinite)[0]:
                bad_meshes[s + int(j)] = int(nonfinite[j])

    cams_in = manifest["cameras"]
    if not isinstance(cams_in, dict):
        problems.add(
            "manifest", f"'cameras' must be an object mapping camera ids to cameras, got {_type_name(cams_in)}"
        )
        cams_in = None
    cameras = {}
    for cid, cam in (cams_in or {}).items():
        ok = _check_camera(str(cid), cam, problems)
        if ok is not None:
            cameras[str(cid)] = (ok[0], ok[1], int(cam["width"]), int(cam["height"]))

    names = set()
    empty: list[int] = []  # frames whose mask is empty: bad frames at the door
    for i, rec in enumerate(frames):
        name = rec.get("name", str(i)) if isinstance(rec, dict) else str(i)
        where = f"frame {i} ({name!r})"
        if not isinstance(rec, dict) or "image" not in rec or "camera" not in rec or "mesh" not in rec:
            problems.add(where, f"needs 'image', 'camera' and 'mesh' (got {_type_name(rec)})")
            continue
        bad_types = [
            f"{k} must be {want}, got {_type_name(rec[k])}"
            for k, want, ok in (
                ("name", "a string", lambda x: isinstance(x, str)),
                ("camera", "a camera id (string)", lambda x: isinstance(x, str) or _is_int(x)),
                ("mesh", "an integer", _is_int),
                ("clip", "a string or null", lambda x: x is None or isinstance(x, str)),
                ("time", "a number or null", lambda x: x is None or _is_number(x)),
            )
            if k in rec and not ok(rec[k])
        ]
        if bad_types:
            problems.add(where, "; ".join(bad_types))
            continue
        rec.setdefault("name", name)
        if name in names:
            problems.add(where, "duplicate frame name")
        names.add(name)
        cid = str(rec["camera"])
        if cams_in is not None and cid not in cams_in:
            problems.add(where, f"unknown camera {cid!r}")
        m = rec["mesh"]
        if verts is not None and not (0 <= m < verts.shape[0]):
            problems.add(where, f"mesh index {m!r} out of range [0, {verts.shape[0]})")
        elif m in bad_meshes:
            problems.add(where, f"driving vertices contain {bad_meshes[m]} NaN/Inf values (mesh {m})")
        cam = (cams_in or {}).get(cid)
        size = (cam.get("width"), cam.get("height")) if isinstance(cam, dict) and cid in cameras else None
        if _check_frame_files(root, rec, where, size, check_masks, problems, allow_outside):
            empty.append(i)
    splits = manifest.get("splits")
    if splits is None:
        splits = {}
    if not isinstance(splits, dict):
        problems.add(
            "manifest", f"'splits' must be an object mapping names to lists of frame indices, got {_type_name(splits)}"
        )
        splits = {}
    for sname, idx in splits.items():
        if not isinstance(idx, list):
            problems.add(f"split {sname!r}", f"must be a list of frame indices, got {_type_name(idx)}")
            continue
        bad = [j for j in idx if not (_is_int(j) and 0 <= j < len(frames))]
        if bad:
            problems.add(f"split {sname!r}", f"frame indices out of range or not integers: {bad[:5]}")
    if not isinstance(manifest.get("meta") or {}, dict):
        problems.add("manifest", f"'meta' must be an object, got {_type_name(manifest.get('meta'))}")
    backdrop = manifest.get("backdrop")
    if backdrop is not None and not (
        isinstance(backdrop, list) and len(backdrop) == 3 and all(_is_number(x) and 0 <= x <= 1 for x in backdrop)
    ):
        problems.add("manifest", f"'backdrop' must be three numbers in [0, 1] (an RGB colour), got {backdrop!r}")
    problems.raise_if_any()
    assert canonical is not None and faces is not None and verts is not None, "a None array comes with a problem"
    manifest["splits"] = splits
    ds = AvatarDataset(
        root,
        manifest,
        canonical,
        faces,
        verts,
        cameras,
        cache_size=cache_size,
        driver_params=driver_params,
        format_name=format_name,
    )
    return _check_at_the_door(ds, drop_bad_frames, check_masks, set(empty))


EMPTY_MASK = "empty mask, the subject left the view"
LISTED_NAMES = 4  # image names listed per reason in a refusal, then how many more


def _names(frames: list[dict], ids: list[int]) -> str:
    """The image names of frames ``ids`` (at most ``LISTED_NAMES``, then how many more)."""
    shown = ", ".join(Path(str(frames[i]["image"])).name for i in ids[:LISTED_NAMES])
    return shown + (f" and {len(ids) - LISTED_NAMES} more" if len(ids) > LISTED_NAMES else "")


def _check_at_the_door(
    ds: AvatarDataset, drop_bad_frames: bool, with_masks: bool, empty: set[int] | None = None
) -> AvatarDataset:
    """Cameras against meshes (and, ``with_masks``, every frame's mask; ``camera_check``): refuse wrong
    cameras, refuse or drop bad frames (with ``empty``: the frames whose mask is empty, dropped too)."""
    frames = ds._frames
    empty = empty or set()

    def load_mask(i: int) -> np.ndarray | None:
        m = ds._load_mask(frames[i]) if with_masks and i not in empty else None
        return None if m is None else m.numpy()

    found = check_cameras(
        ds._cameras, [(str(r["camera"]), int(r["mesh"])) for r in frames], ds._verts, load_mask, ds.faces.numpy()
    )
    if found.wrong:
        raise MeshsplatError(
            f"{ds.root}: wrong camera{'s' if len(found.wrong) > 1 else ''}: " + "; ".join(found.wrong.values())
        )

    def note_unsized() -> None:  # once the capture opens: the frames whose camera distance went unchecked
        if found.unsized:
            ids = sorted(found.unsized)
            warnings.warn(
                f"{ds.root}: the masks of {len(ids)} of {len(frames)} frames fill the image ({_names(frames, ids)}): "
                "nothing in them shows the subject's size, so their camera's distance to it was not checked",
                MeshsplatWarning,
                stacklevel=4,
            )

    found.bad_frames.update(dict.fromkeys(empty, EMPTY_MASK))
    if not found.bad_frames:
        note_unsized()
        return ds
    bad = sorted(found.bad_frames)
    reasons: dict[str, list[int]] = {}
    for i in bad:
        reasons.setdefault(found.bad_frames[i], []).append(i)
    listed = "; ".join(f"{why}: {_names(frames, ids)}" for why, ids in reasons.items())
    n, n_all = len(bad), len(frames)
    if n == n_all:  # nothing would be left to train on: dropping is no way out
        if set(reasons) == {EMPTY_MASK}:
            raise MeshsplatError(
                f"{ds.root}: every mask is empty ({n} frames): give the masks of the subject, white on black"
            )
        raise MeshsplatError(f"{ds.root}: every frame fails the camera check ({listed}); fix the cameras or the masks")
    if not drop_bad_frames:  # one line: the problem, at most a few image names per reason, what to do
        if set(reasons) == {EMPTY_MASK}:
            what = f"the subject left the view in {n} of {n_all} frames (empty masks: {_names(frames, bad)})"
        else:
            what = f"{n} of {n_all} frames do not show the subject where their camera puts the mesh ({listed})"
        raise MeshsplatError(f"{ds.root}: {what}; leave them out with {DROP_FLAG}, or fix their masks or cameras")
    warnings.warn(f"{ds.root}: left out {n} of {n_all} frames ({listed})", MeshsplatWarning, stacklevel=3)
    note_unsized()
    drop = set(bad)
    new_index: dict[int, int] = {}
    kept: list[dict] = []
    for i, rec in enumerate(frames):
        if i not in drop:
            new_index[i] = len(kept)
            kept.append(rec)
    manifest = dict(ds.manifest)
    manifest["frames"] = kept
    manifest["splits"] = {k: [new_index[i] for i in v if i in new_index] for k, v in ds._splits.items()}
    manifest["meta"] = {
        **(manifest.get("meta") or {}),
        "dropped_frames": [str(frames[i]["name"]) for i in bad],
        "dropped_reason": listed,
    }
    return AvatarDataset(
        ds.root,
        manifest,
        ds.canonical_vertices.numpy(),
        ds.faces.numpy(),
        ds._verts,
        ds._cameras,
        cache_size=ds._cache_size,
        driver_params=ds.driver_params,
        format_name=ds.format_name,
    )


def _check_frame_files(
    root: Path,
    rec: dict,
    where: str,
    size,
    check_masks: bool,
    problems: Problems,
    allow_outside: bool,
) -> bool:
    """Image and mask of one frame record: present, decodable header, the camera's size.
    Returns whether the mask is empty (the subject left the view: a bad frame for the check at the door,
    which refuses it in one line with the others or leaves it out with ``drop_bad_frames``)."""
    kind = rec.get("mask_kind", "png")
    if kind not in MASK_KINDS:
        problems.add(where, f"mask_kind {kind!r} is not one of {list(MASK_KINDS)}")
        return False
    checks = [("image", rec.get("image"))]
    if rec.get("mask") is not None and kind != "alpha":
        checks.append(("mask", rec["mask"]))
    for what, value in checks:
        rel = inside_capture(root, value, f"{what} path", where, problems, allow_outside)
        if rel is None:
            return False
        p = root / rel
        if not p.is_file():
            problems.add(where, f"{what} file {rel} is missing")
            return False
        try:
            if what == "mask" and kind == "npy":
                arr = read_npy(p, "mask array", mmap=True)
                shape = tuple(int(x) for x in np.squeeze(np.empty(arr.shape, np.uint8)).shape)
                wh = (shape[1], shape[0]) if len(shape) == 2 else None
                if wh is None:
                    problems.add(where, f"mask {rel} has shape {list(arr.shape)}, expected [H,W]")
                    continue
            else:
                wh = image_size(p)
        except (MeshsplatError, OSError, ValueError):
            problems.add(
                where, f"{what} file {rel} is not a readable {'array' if kind == 'npy' and what == 'mask' else 'image'}"
            )
            return False
        if size is not None and wh != size:
            problems.add(
                where,
                f"{what} size mismatch: {rel} is {wh[0]}x{wh[1]} but camera {rec['camera']!r} says {size[0]}x{size[1]}",
            )
            return False
    if not check_masks or not (rec.get("mask") or kind == "alpha"):
        return False
    try:
        if kind == "alpha":
            img = read_image(root / rec["image"], 4)
            m = img[..., 3]
            if (m == 255).all():
                problems.add(where, f"mask_kind 'alpha' but {rec['image']} has no alpha channel (or it is all opaque)")
                return False
        elif kind == "npy":
            m = _read_npy_mask(root / rec["mask"])
        else:
            m = read_mask(root / rec["mask"])[0]  # as training reads it (alpha mattes, 0/1 label maps)
    except MeshsplatError as exc:
        problems.add(where, str(exc))
        return False
    return float(m.max()) == 0
