"""Write a self-contained WebGL2 viewer bundle that animates an avatar in a browser.

    write_viewer_bundle(avatar, frames, "out/viewer", fps=25)   # -> out/viewer/index.html

The bundle folder holds ``index.html`` (self-contained: viewer code, ``avatar.json`` and base64
``avatar.bin`` inlined, so it opens from ``file://``), plus ``viewer.js``, ``avatar.bin`` and
``avatar.json`` as separate files for tools and tests. ``avatar.bin`` is little-endian; each
section of ``avatar.json["sections"]`` gives its byte ``offset`` (4-byte aligned), ``dtype``
(float32, uint32, int16) and ``shape``. The Gaussians are packed into 32 bytes each (face index
plus half floats, :func:`pack_gaussians`), their higher SH bands into ``sh_rest`` (half floats).
The browser poses and shades the Gaussians from the mesh each frame on the GPU exactly as
:func:`meshsplat.gaussians.compose` does (view-dependent colour, the learned irradiance of the
posed normal, the shadowed key light of ``shading.occlusion=key``, antialiasing compensation). See
docs/viewer.md.
"""

from __future__ import annotations

import base64
import html
import json
import math
import re
import urllib.parse
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from meshsplat._checks import check_tensor
from meshsplat._typing import ArrayLike
from meshsplat.animation import Animation
from meshsplat.camera import Camera, intrinsics, orbit_basis, orbit_cameras, orbit_viewmat
from meshsplat.drivers import BlendshapeDriver, GltfDriver
from meshsplat.errors import MeshsplatError
from meshsplat.gaussians.avatar import Avatar
from meshsplat.gaussians.compose import effective_uv
from meshsplat.gaussians.params import SH_C0
from meshsplat.gaussians.shading import KEY_STAGES
from meshsplat.io.atomic import write_bytes_atomic, write_text_atomic
from meshsplat.io.json_file import read_json_object
from meshsplat.viewer.rig import bundle_rig, rig_preview_frames
from meshsplat.viewer.webcam import copy_landmarker, find_landmarker

__all__ = [
    "write_viewer_bundle",
    "read_viewer_bundle",
    "default_camera",
    "page_camera",
    "pack_gaussians",
    "unpack_gaussians",
    "BUNDLE_VERSION",
    "VERTEX_ENCODINGS",
]

BUNDLE_VERSION = 3
VERTEX_ENCODINGS = ("int16", "float32")
_STATIC = Path(__file__).parent / "static"
_DTYPES: dict[str, np.dtype] = {
    "float32": np.dtype("<f4"),
    "uint32": np.dtype("<u4"),
    "int16": np.dtype("<i2"),
    "int32": np.dtype("<i4"),
}


def _as_frames(frames, num_vertices: int) -> np.ndarray:
    """[T,V,3] float64 numpy from a tensor/array [T,V,3] or a sequence of [V,3]."""
    if isinstance(frames, (torch.Tensor, np.ndarray)):
        if frames.ndim != 3:
            raise MeshsplatError(f"frames: expected shape [T,{num_vertices},3], got {list(frames.shape)}")
        seq = list(frames)
    elif isinstance(frames, Sequence):
        seq = list(frames)
    else:
        raise MeshsplatError(f"frames: expected a [T,V,3] tensor or a list of [V,3], got {type(frames).__name__}")
    if not seq:
        raise MeshsplatError("frames: the animation has no frames")
    out = []
    for i, v in enumerate(seq):
        v = torch.as_tensor(np.asarray(v)) if not isinstance(v, torch.Tensor) else v
        check_tensor(f"frames[{i}]", v, "V,3", {"V": num_vertices}, dtype="float", finite=True)
        out.append(v.detach().cpu().double().numpy())
    return np.stack(out)


def default_camera(
    frames: np.ndarray,
    width: int = 800,
    height: int = 800,
    azimuth_deg: float = 0.0,
    elevation_deg: float = 10.0,
    fov_deg: float = 30.0,
    up: ArrayLike = (0.0, 1.0, 0.0),
    front: ArrayLike = (0.0, 0.0, 1.0),
) -> dict[str, Any]:
    """Orbit camera framing all ``frames [T,V,3]`` (as ``meshsplat.camera.orbit_cameras``), turning about
    ``up`` from ``front`` (a capture's: ``dataset.up``, ``dataset.front``)."""
    lo, hi = frames.reshape(-1, 3).min(0), frames.reshape(-1, 3).max(0)
    cam = orbit_cameras(
        [torch.from_numpy(np.stack([lo, hi]))],
        width,
        height,
        azimuth_deg=azimuth_deg,
        elevation_deg=elevation_deg,
        fov_deg=fov_deg,
        up=up,
        front=front,
    )[0]
    center = (lo + hi) / 2
    eye = -cam.viewmat[:3, :3].double().T @ cam.viewmat[:3, 3].double()
    return _camera_dict(
        center,
        float(np.linalg.norm(eye.numpy() - center)),
        azimuth_deg,
        elevation_deg,
        fov_deg,
        width,
        height,
        up,
        front,
    )


def _camera_dict(
    center, distance, azimuth_deg, elevation_deg, fov_deg, width, height, up=(0.0, 1.0, 0.0), front=(0.0, 0.0, 1.0)
) -> dict[str, Any]:
    _, u, f = orbit_basis(up, front)
    vm = orbit_viewmat(center, distance, azimuth_deg, elevation_deg, u, f)
    return {
        "up": [float(x) for x in u],
        "front": [float(x) for x in f],
        "center": [float(x) for x in center],
        "distance": float(distance),
        "azimuth_deg": float(azimuth_deg),
        "elevation_deg": float(elevation_deg),
        "fov_deg": float(fov_deg),
        "width": int(width),
        "height": int(height),
        "viewmat": vm.tolist(),
        "K": intrinsics(width, height, fov_deg).tolist(),
    }


def _vec(x) -> np.ndarray:
    return np.asarray(x.detach().cpu() if isinstance(x, torch.Tensor) else x, np.float64).reshape(3)


def _camera_from(camera, frames: np.ndarray) -> dict[str, Any]:
    """Orbit description of ``camera``: None (auto), a dict of overrides, or a ``camera.Camera``."""
    if camera is None:
        return default_camera(frames)
    if isinstance(camera, dict):
        allowed = {"width", "height", "azimuth_deg", "elevation_deg", "fov_deg", "distance", "center", "up", "front"}
        unknown = set(camera) - allowed
        if unknown:
            raise MeshsplatError(f"camera: unknown key(s) {sorted(unknown)} (allowed: {sorted(allowed)})")
        base = default_camera(
            frames,
            camera.get("width", 800),
            camera.get("height", 800),
            camera.get("azimuth_deg", 0.0),
            camera.get("elevation_deg", 10.0),
            camera.get("fov_deg", 30.0),
            _vec(camera.get("up", (0.0, 1.0, 0.0))),
            _vec(camera.get("front", (0.0, 0.0, 1.0))),
        )
        center = np.asarray(camera.get("center", base["center"]), np.float64)
        return _camera_dict(
            center,
            float(camera.get("distance", base["distance"])),
            base["azimuth_deg"],
            base["elevation_deg"],
            base["fov_deg"],
            base["width"],
            base["height"],
            base["up"],
            base["front"],
        )
    if isinstance(camera, Camera):
        # world->camera (OpenCV, no roll) -> orbit about the point of the view axis nearest the animation centre
        vm = camera.viewmat.detach().cpu().double().numpy()
        R, t = vm[:3, :3], vm[:3, 3]
        eye, fwd = -R.T @ t, R[2]
        mid = (frames.reshape(-1, 3).min(0) + frames.reshape(-1, 3).max(0)) / 2
        dist = max(float(np.dot(mid - eye, fwd)), 1e-6)
        el = math.degrees(math.asin(float(np.clip(-fwd[1], -1, 1))))
        az = math.degrees(math.atan2(-fwd[0], -fwd[2]))
        fov = math.degrees(2 * math.atan(0.5 * camera.height / float(camera.K[1, 1])))
        return _camera_dict(eye + dist * fwd, dist, az, el, fov, camera.width, camera.height)
    raise MeshsplatError(f"camera: expected None, a dict or a meshsplat.camera.Camera, got {type(camera).__name__}")


def _encode_vertices(frames: np.ndarray, encoding: str) -> tuple[np.ndarray, dict[str, Any]]:
    if encoding == "float32":
        return frames.astype("<f4"), {}
    lo, hi = frames.reshape(-1, 3).min(0), frames.reshape(-1, 3).max(0)
    offset = (lo + hi) / 2
    step = np.maximum((hi - lo) / 2 / 32767.0, 1e-12)
    q = np.clip(np.rint((frames - offset) / step), -32767, 32767).astype("<i2")
    return q, {"vertex_offset": offset.tolist(), "vertex_step": step.tolist()}


def _gaussian_arrays(avatar) -> dict[str, np.ndarray]:
    """Per-Gaussian arrays the viewer needs (float64 except ``face``), keyed as read_viewer_bundle returns them."""
    p = avatar.params
    with torch.no_grad():
        rot = p["rotation"].detach().double()
        rot = rot / rot.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        return {
            "gaussian_face": p["face"].detach().cpu().numpy().astype("<u4"),
            "gaussian_uv": effective_uv(p, avatar.clamp_to_face).detach().double().cpu().numpy(),
            "gaussian_d": p["d"].detach().double().cpu().numpy(),
            "gaussian_rotation": rot.cpu().numpy(),
            "gaussian_scale": p["log_scale"].detach().double().exp().cpu().numpy(),
            "gaussian_opacity": torch.sigmoid(p["opacity_logit"].detach().double()).cpu().numpy(),
            # 0.5 + C0 sh0, not clamped: the page adds the view-dependent bands, clamps, then shades
            "gaussian_rgb": (0.5 + SH_C0 * p["sh0"].detach().double()[:, 0]).cpu().numpy(),
        }


def _sh_rest(avatar: Avatar) -> np.ndarray | None:
    """``[N, W]`` uint32: the SH bands above 0 (``shN [N,K,3]``, coefficient-major) as half-float pairs,
    ``W`` padded to a multiple of 4 (whole RGBA32UI texels); None for SH degree 0."""
    shn = avatar.params.get("shN")
    if shn is None or shn.shape[1] == 0:
        return None
    flat = shn.detach().double().cpu().numpy().reshape(len(shn), -1)  # [N, 3K]: k-th coefficient's r, g, b
    if not np.isfinite(flat).all() or np.abs(flat).max(initial=0) > 65504:
        raise MeshsplatError("avatar: SH coefficients beyond the half-float range of the viewer")
    words = -(-flat.shape[1] // 2)
    words += (-words) % 4
    halves = np.zeros((len(flat), 2 * words), np.float64)
    halves[:, : flat.shape[1]] = flat
    bits = _half_bits(halves)
    return np.ascontiguousarray(bits[:, 0::2] | (bits[:, 1::2] << 16)).astype("<u4")


def _check_occlusion(avatar: Avatar) -> None:
    """The player shades ``shading.occlusion=none`` and an aligned ``key`` (its shadow maps built per frame)."""
    sh = avatar.shading
    if sh is None or sh.occlusion == "none" or (sh.occlusion == "key" and sh.key_aligned):
        return
    if sh.occlusion == "key":
        raise MeshsplatError(
            f"avatar: shading.occlusion=key with the key light not aligned yet (stage {sh.key_stage} of "
            f"{KEY_STAGES}; the web player shades one key light); train to {KEY_STAGES} x "
            "shading.key_iter or use meshsplat render for this avatar"
        )
    raise MeshsplatError(
        f"avatar: trained with shading.occlusion={sh.occlusion}, which the web player does not shade (one "
        "shadow map per light direction and frame; it shades shading.occlusion=key); use meshsplat render for this avatar"
    )


def _shading_header(avatar: Avatar) -> dict[str, Any]:
    """What the page needs to colour the Gaussians as ``compose`` does."""
    sh = avatar.shading
    shading: dict[str, Any] | None = None
    if sh is not None:
        shading = {"coeffs": sh.coeffs.detach().double().cpu().tolist(), "normal": sh.normal, "space": "world"}
        if sh.specular is not None:  # added after the albedo multiply (shading.specular=sh2)
            shading["specular"] = sh.specular.detach().double().cpu().tolist()
        if sh.occlusion == "key":  # one shadowed key light (shading.occlusion=key, aligned): E += L V(x) max(0, n . w)
            shadows = sh.shadow_directions()  # V(x): the mean over these directions' height maps
            assert sh.directions is not None and sh.light is not None and shadows is not None
            shading["key"] = {
                "direction": sh.directions[0].detach().double().cpu().tolist(),
                "light": sh.light[0].detach().double().clamp_min(0.0).cpu().tolist(),
                "grid": sh.grid,
                "shadows": shadows.detach().double().cpu().tolist(),
            }
    return {
        "sh_degree": avatar.sh_degree,
        "sh_frame": avatar.sh_frame,
        "antialiased": avatar.antialiased,
        "shading": shading,
    }


# Packed Gaussian: 8 little-endian uint32 words; "a|b" = two IEEE half floats, a in the low 16 bits
# (GLSL unpackHalf2x16 order): face, u|v, d|opacity, r|g, qw|qx, qy|qz, s0|s1, s2|b.
_HALF_PAIRS = (
    ("uv", 0, "uv", 1),
    ("d", None, "opacity", None),
    ("rgb", 0, "rgb", 1),
    ("rot", 0, "rot", 1),
    ("rot", 2, "rot", 3),
    ("scale", 0, "scale", 1),
    ("scale", 2, "rgb", 2),
)
_PACK_KEYS = {
    "uv": "gaussian_uv",
    "d": "gaussian_d",
    "opacity": "gaussian_opacity",
    "rgb": "gaussian_rgb",
    "rot": "gaussian_rotation",
    "scale": "gaussian_scale",
}


def _half_bits(x: np.ndarray) -> np.ndarray:
    with np.errstate(over="ignore"):
        return np.asarray(x, np.float64).astype(np.float16).view(np.uint16).astype(np.uint32)


def pack_gaussians(arrays: dict[str, np.ndarray]) -> np.ndarray:
    """``[N, 8]`` uint32 packing of the viewer's per-Gaussian arrays (half floats, round to nearest even).

    Half floats keep 11 significant bits: relative error <= 2^-11 (0.05%) on uv, d, rotation,
    scale, colour and opacity for |x| >= 6.1e-5 (absolute <= 3e-8 below, where halves are
    subnormal). A value beyond the half range (|x| > 65504, e.g. a scale in a mesh of huge units)
    raises an error.
    """
    n = len(arrays["gaussian_face"])
    out = np.empty((n, 8), "<u4")
    out[:, 0] = arrays["gaussian_face"]
    for w, (ka, ia, kb, ib) in enumerate(_HALF_PAIRS, start=1):
        a, b = arrays[_PACK_KEYS[ka]], arrays[_PACK_KEYS[kb]]
        a, b = (a if ia is None else a[:, ia]), (b if ib is None else b[:, ib])
        if (
            not (np.isfinite(a).all() and np.isfinite(b).all())
            or max(np.abs(a).max(initial=0), np.abs(b).max(initial=0)) > 65504
        ):
            raise MeshsplatError(
                f"avatar: {ka}/{kb} values beyond the half-float range of the viewer "
                "(|x| > 65504 or not finite); rescale the mesh units"
            )
        out[:, w] = _half_bits(a) | (_half_bits(b) << 16)
    return out


def unpack_gaussians(packed: np.ndarray) -> dict[str, np.ndarray]:
    """Inverse of :func:`pack_gaussians` (float32 arrays holding the half-float values)."""
    packed = np.asarray(packed, "<u4")
    n = packed.shape[0]
    cols: dict[str, np.ndarray] = {
        "uv": np.empty((n, 2)),
        "rgb": np.empty((n, 3)),
        "rot": np.empty((n, 4)),
        "scale": np.empty((n, 3)),
        "d": np.empty(n),
        "opacity": np.empty(n),
    }
    for w, (ka, ia, kb, ib) in enumerate(_HALF_PAIRS, start=1):
        lo = (packed[:, w] & 0xFFFF).astype(np.uint16).view(np.float16).astype(np.float64)
        hi = (packed[:, w] >> 16).astype(np.uint16).view(np.float16).astype(np.float64)
        for key, idx, val in ((ka, ia, lo), (kb, ib, hi)):
            if idx is None:
                cols[key][:] = val
            else:
                cols[key][:, idx] = val
    out = {_PACK_KEYS[k]: v.astype("<f4") for k, v in cols.items()}
    out["gaussian_face"] = packed[:, 0].copy()
    return out


def _pack(sections: dict[str, np.ndarray]) -> tuple[bytes, dict[str, Any]]:
    chunks, layout, offset = [], {}, 0
    for name, arr in sections.items():
        arr = np.ascontiguousarray(arr)
        dtype = next(k for k, d in _DTYPES.items() if arr.dtype == d)
        raw = arr.tobytes()
        layout[name] = {"offset": offset, "dtype": dtype, "shape": list(arr.shape)}
        pad = (-len(raw)) % 4
        chunks.append(raw + b"\0" * pad)
        offset += len(raw) + pad
    return b"".join(chunks), layout


def write_viewer_bundle(
    avatar: Avatar,
    frames: ArrayLike | Animation | None,
    out_dir: str | Path,
    fps: float | None = None,
    camera: Camera | dict[str, Any] | None = None,
    title: str = "meshsplat avatar",
    vertex_encoding: str = "int16",
    background: str = "white",
    rig: GltfDriver | BlendshapeDriver | None = None,
    webcam: tuple[dict[str, np.ndarray], dict[str, Any]] | None = None,
    landmarker: str | Path | None = None,
) -> Path:
    """Write the viewer for ``avatar`` animated by ``frames`` (``[T,V,3]`` tensor/array, a list of ``[V,3]``,
    or an :class:`~meshsplat.animation.Animation` from ``load_animation``: its frames, or its driver
    live when loaded with ``live=True``) or, live, by ``rig``: a ``GltfDriver`` on the avatar's canonical vertices (e.g. from
    :func:`meshsplat.viewer.rig.avatar_driver`: its skin, morph targets and clips ship in the bundle)
    or a ``BlendshapeDriver`` on them (expressions as morph targets, its sequence a clip at ``fps``);
    the page evaluates them, and ``frames`` is then None or only used to frame the camera.

    ``camera``: None (orbit auto-framed on the animation, 800x800, 30° fov), a dict overriding
    ``width, height, azimuth_deg, elevation_deg, fov_deg, distance, center, up, front`` (the orbit turns
    about ``up``, default +y, from ``front``, default +z; a capture's: ``dataset.up``, ``dataset.front``), or an
    ``camera.Camera`` (turned into an orbit; roll is dropped). ``webcam``: the landmark model of
    :func:`meshsplat.viewer.webcam.webcam_model` (a live rig with morph targets of its ARKit names
    needed): the page gets a webcam mode, and the face landmarker (``@mediapipe/face_mesh``, found by
    :func:`~meshsplat.viewer.webcam.find_landmarker` from ``landmarker``) is copied beside it. ``vertex_encoding``: "int16"
    (per-axis step over the animation's box, error <= step/2) or "float32". ``fps``: frame rate of
    ``frames`` (default the Animation's, else 25; with a glTF rig unused; with a blendshape rig the rate of
    its sequence). Returns ``index.html``.
    """
    if isinstance(frames, Animation):
        fps = frames.fps if fps is None else fps
        if frames.driver is not None:
            if rig is not None:
                raise MeshsplatError("rig: given twice (the Animation is live already)")
            rig, frames = frames.driver, None
        else:
            frames = frames.frames
    fps = 25.0 if fps is None else fps
    if not isinstance(avatar, Avatar):
        raise MeshsplatError(f"avatar: expected an Avatar, got {type(avatar).__name__}")
    _check_occlusion(avatar)
    if not (isinstance(fps, (int, float)) and math.isfinite(fps) and fps > 0):
        raise MeshsplatError(f"fps: expected > 0, got {fps}")
    if vertex_encoding not in VERTEX_ENCODINGS:
        raise MeshsplatError(f"vertex_encoding: expected one of {VERTEX_ENCODINGS}, got {vertex_encoding!r}")
    if background not in ("white", "black"):
        raise MeshsplatError(f"background: expected 'white' or 'black', got {background!r}")
    mesh = avatar.mesh
    sections: dict[str, np.ndarray] = {
        "faces": mesh.faces.detach().cpu().numpy().astype("<u4"),
        "canonical_vertices": mesh.vertices.detach().cpu().numpy().astype("<f4"),
    }
    quant: dict[str, Any] = {}
    if rig is not None:
        rig_sections, driver, rig_vertices = bundle_rig(rig, fps)
        if rig_vertices != mesh.num_vertices:
            raise MeshsplatError(
                f"rig: drives {rig_vertices} vertices, the avatar's mesh has {mesh.num_vertices} "
                "(load it with meshsplat.animation.load_animation(source, avatar, live=True))"
            )
        sections.update(rig_sections)
        if frames is None:  # frame the camera on samples of the default clip
            frames = rig_preview_frames(rig)
        verts = _as_frames(frames, mesh.num_vertices)
        num_frames = 0
    else:
        verts = _as_frames(frames, mesh.num_vertices)
        encoded, quant = _encode_vertices(verts, vertex_encoding)
        sections["frames"] = encoded
        driver = {"kind": "frames"}
        num_frames = int(verts.shape[0])
    sections["gaussians"] = pack_gaussians(_gaussian_arrays(avatar))
    sh_rest = _sh_rest(avatar)
    if sh_rest is not None:
        sections["sh_rest"] = sh_rest
    webcam_header = None
    landmarker_dir = None
    if webcam is not None:
        webcam_header = _webcam_targets(webcam[1], driver)
        landmarker_dir = find_landmarker(landmarker)
        sections.update(webcam[0])
    blob, layout = _pack(sections)
    header = {
        "format": "meshsplat-viewer",
        "version": BUNDLE_VERSION,
        "title": str(title),
        "num_vertices": mesh.num_vertices,
        "num_faces": mesh.num_faces,
        "num_gaussians": avatar.num_gaussians,
        "num_frames": num_frames,
        "fps": float(fps),
        "scale_mode": avatar.scale_mode,
        **_shading_header(avatar),
        "vertex_encoding": vertex_encoding,
        **quant,
        "background": background,
        "camera": _camera_from(camera, verts),
        "driver": driver,
        **({"webcam": webcam_header} if webcam_header is not None else {}),
        "sections": layout,
    }
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    viewer_js = (_STATIC / "viewer.js").read_text(encoding="utf-8")
    if "</script" in viewer_js.lower():
        raise MeshsplatError("viewer.js must not contain '</script' (it is inlined into index.html)")
    header_json = json.dumps(header, indent=1)
    page = _fill_template(
        (_STATIC / "index.html").read_text(encoding="utf-8"),
        {
            "TITLE": html.escape(str(title)),
            "AVATAR_HEADER": header_json.replace("<", "\\u003c"),  # no "</script" or "<!--" inside the JSON
            "AVATAR_DATA": base64.b64encode(blob).decode("ascii"),
            "VIEWER_JS": viewer_js,
        },
    )
    # each file to a temporary name, then renamed: a full disk leaves no truncated page or data
    write_bytes_atomic(out / "avatar.bin", blob)
    write_text_atomic(out / "avatar.json", header_json + "\n")
    write_text_atomic(out / "viewer.js", viewer_js)
    if landmarker_dir is not None:
        copy_landmarker(landmarker_dir, out)
    index = out / "index.html"
    write_text_atomic(index, page)
    return index


def _webcam_targets(model: dict[str, Any], driver: dict[str, Any]) -> dict[str, Any]:
    """The webcam model's header plus ``targets``: the rig's morph weight index of each of its shapes
    (-1 where the avatar has no target of that name)."""
    if driver.get("kind") != "gltf" or not driver.get("morph_groups"):
        raise MeshsplatError(
            "webcam: needs a live blend-shape head (--animation blendshapes, or a glTF rig with ARKit-named "
            "morph targets), not vertex frames"
        )
    index: dict[str, int] = {}
    for g in driver["morph_groups"]:
        for m, name in enumerate(g["names"]):
            index.setdefault(str(name), g["weight_base"] + m)
    targets = [int(index.get(n, -1)) for n in model["names"]]
    if all(t < 0 for t in targets):
        raise MeshsplatError(
            "webcam: the avatar's morph targets have none of the ARKit names the face solve gives "
            f"({', '.join(model['names'][:4])}, ...)"
        )
    return {**model, "targets": targets}


def _fill_template(template: str, values: dict[str, str]) -> str:
    """Replace each ``__NAME__`` of the template in ONE pass, so that inserted text (a title such as
    ``__VIEWER_JS__``, the viewer source, the data) is never scanned for placeholders again."""
    return re.sub(r"__(TITLE|AVATAR_HEADER|AVATAR_DATA|VIEWER_JS)__", lambda m: values[m.group(1)], template)


def parse_view(text: str) -> dict[str, Any]:
    """The orbit entries of a page's ``view=AZ,EL,DIST,CX,CY,CZ,FOV,W,H`` (the player's URL fragment and
    "copy view", ``viewString`` in viewer.js): ``azimuth_deg, elevation_deg, distance, center, fov_deg,
    width, height``."""
    m = re.search(r"(?:^|[#&])view=([^&#]*)", text)
    if m is None:
        raise MeshsplatError(
            f"page view: expected view=AZ,EL,DIST,CX,CY,CZ,FOV,W,H (the page's #view=...), got {text!r}"
        )
    try:
        v = [float(x) for x in m.group(1).split(",")]
    except ValueError:
        v = []
    if len(v) != 9 or not all(math.isfinite(x) for x in v) or v[2] <= 0 or v[7] < 1 or v[8] < 1:
        raise MeshsplatError(
            f"page view: expected 9 numbers AZ,EL,DIST,CX,CY,CZ,FOV,W,H (distance > 0, a size in pixels), got {m.group(1)!r}"
        )
    return {
        "azimuth_deg": v[0],
        "elevation_deg": v[1],
        "distance": v[2],
        "center": (v[3], v[4], v[5]),
        "fov_deg": v[6],
        "width": round(v[7]),
        "height": round(v[8]),
    }


def page_camera(path: str | Path) -> dict[str, Any]:
    """The player page's camera as an orbit description (``meshsplat.camera.ORBIT_KEYS``: ``center,
    distance, azimuth_deg, elevation_deg, fov_deg, width, height, up, front``) from a viewer bundle folder,
    its ``avatar.json`` or its ``index.html`` (a path or a ``file://`` URL): the initial camera, or, with a
    ``#view=...`` fragment (the page's address, "copy view"), the view the page showed; ``meshsplat.camera.
    orbit_camera(**it)`` is the page's camera."""
    text = str(path)
    view = None
    if "#" in text:
        text, fragment = text.split("#", 1)
        view = parse_view(fragment)
    if text.startswith("file://"):
        text = urllib.parse.unquote(urllib.parse.urlparse(text).path)
    p = Path(text)
    p = p.parent if p.name == "index.html" else p
    p = p / "avatar.json" if p.is_dir() else p
    try:
        cam = json.loads(p.read_text(encoding="utf-8")).get("camera")
    except FileNotFoundError:
        raise MeshsplatError(f"{p}: not found (expected a viewer folder or its avatar.json)") from None
    except (ValueError, UnicodeDecodeError, AttributeError) as exc:
        raise MeshsplatError(f"{p}: not a viewer bundle header ({exc})") from None
    need = ("center", "distance", "azimuth_deg", "elevation_deg", "fov_deg", "width", "height")
    if not isinstance(cam, dict) or any(k not in cam for k in need):
        raise MeshsplatError(f"{p}: has no page camera ({', '.join(need)}); write the viewer again with this meshsplat")
    try:
        out: dict[str, Any] = {k: float(cam[k]) for k in ("distance", "azimuth_deg", "elevation_deg", "fov_deg")}
        out["width"], out["height"] = int(cam["width"]), int(cam["height"])
        for k, default in (("center", None), ("up", (0.0, 1.0, 0.0)), ("front", (0.0, 0.0, 1.0))):
            v = np.asarray(cam.get(k, default), np.float64)
            if v.shape != (3,) or not np.isfinite(v).all():
                raise ValueError(f"{k} is not a finite 3-vector")
            out[k] = tuple(float(x) for x in v)
    except (TypeError, ValueError) as exc:
        raise MeshsplatError(f"{p}: page camera: {exc}") from None
    if view is not None:
        out.update(view)
    return out


def read_viewer_bundle(out_dir: str | Path) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """``(header, arrays)`` of a bundle folder; ``arrays["vertices"]`` holds the decoded frames ``[T,V,3]``
    (vertex-frame bundles) and ``gaussian_*`` the unpacked per-Gaussian arrays (the half-float values
    the page uses)."""
    root = Path(out_dir)
    for name in ("avatar.json", "avatar.bin"):
        if not (root / name).is_file():
            raise MeshsplatError(f"{root}: not a viewer bundle ({root / name} missing)")
    header = read_json_object(root / "avatar.json", "a viewer bundle header (a JSON object)")
    blob = (root / "avatar.bin").read_bytes()
    arrays = {}
    for name, s in header["sections"].items():
        dt = _DTYPES[s["dtype"]]
        count = int(np.prod(s["shape"])) if s["shape"] else 1
        if s["offset"] + count * dt.itemsize > len(blob):
            raise MeshsplatError(f"{root / 'avatar.bin'}: section {name!r} runs past the end of the file")
        arrays[name] = np.frombuffer(blob, dt, count, s["offset"]).reshape(s["shape"])
    if header.get("version") != BUNDLE_VERSION or "gaussians" not in arrays:
        raise MeshsplatError(
            f"{root}: viewer bundle version {header.get('version')} (expected {BUNDLE_VERSION}); "
            "write it again with this meshsplat"
        )
    arrays.update(unpack_gaussians(arrays["gaussians"]))
    if "sh_rest" in arrays:  # [N, W] half pairs -> [N, K, 3]
        k = {1: 3, 2: 8, 3: 15}[header["sh_degree"]]
        w = arrays["sh_rest"]
        halves = np.stack([w & 0xFFFF, w >> 16], -1).reshape(len(w), -1)[:, : 3 * k]
        arrays["gaussian_sh_rest"] = halves.astype(np.uint16).view(np.float16).astype("<f4").reshape(-1, k, 3)
    if "frames" in arrays:
        frames = arrays["frames"].astype(np.float64)
        if header["vertex_encoding"] == "int16":
            frames = np.asarray(header["vertex_offset"]) + frames * np.asarray(header["vertex_step"])
        arrays["vertices"] = frames
    return header, arrays
