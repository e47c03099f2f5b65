"""Export an avatar: a standard 3DGS ``.ply`` in the canonical pose (and/or antimatter15 ``.splat``,
Niantic ``.spz``, glTF ``KHR_gaussian_splatting`` ``.glb``: ``formats``), the mesh embedding as JSON
and the canonical mesh as OBJ, with a README; and load such an export back into an :class:`Avatar`.

The embedding JSON stores the effective barycentric coordinate the renderer uses (``uv + duv``,
projected onto the triangle for ``clamp_to_face`` avatars), so the re-loaded avatar has ``duv = 0``
and ``clamp_to_face = False`` and composes bit-identical Gaussians in every pose.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any

import torch

from meshsplat.embedding import embed
from meshsplat.errors import MeshsplatError
from meshsplat.gaussians.avatar import Avatar
from meshsplat.gaussians.compose import ComposedGaussians, effective_uv
from meshsplat.gaussians.params import make_params, rgb_to_sh0
from meshsplat.gaussians.shading import Shading
from meshsplat.io import read_embedding_json, read_obj, write_embedding_json, write_gaussian_ply, write_obj
from meshsplat.io.atomic import write_text_atomic, write_with
from meshsplat.io.splat_formats import write_gltf_splats, write_splat, write_spz
from meshsplat.mesh import TriMesh

__all__ = [
    "ExportResult",
    "export_avatar",
    "load_exported_avatar",
    "canonical_gaussians",
    "PLY_NAME",
    "EMBEDDING_NAME",
    "MESH_NAME",
    "SPLAT_FORMATS",
]

PLY_NAME = "avatar.ply"
EMBEDDING_NAME = "embedding.json"
MESH_NAME = "canonical_mesh.obj"
# format -> file name of the static canonical-pose splats
SPLAT_FORMATS = {"ply": PLY_NAME, "splat": "avatar.splat", "spz": "avatar.spz", "gltf": "avatar.glb"}


@dataclass
class ExportResult:
    folder: Path
    ply: Path | None
    embedding: Path
    mesh: Path
    readme: Path
    splats: dict[str, Path] = field(default_factory=dict)  # format -> file, "ply" included


_README = """meshsplat avatar export
=======================

Source: {source}
Gaussians: {n}, SH degree {sh}, scale mode {scale_mode}{clamp}.

{splat_files}{ply}  Standard 3D Gaussian Splatting PLY (binary little endian) in the CANONICAL pose,
    loadable by 3DGS viewers. Per Gaussian: x y z (mean), nx ny nz (Phong normal of the
    mesh at the Gaussian), f_dc_0..2 (SH DC colour: rgb = 0.5 + 0.28209479 * f_dc),
    f_rest_0..44 (higher SH bands, channel-major, zero-padded to degree 3), opacity
    (logit: alpha = sigmoid(opacity)), scale_0..2 (log of the axis lengths), rot_0..3
    (unit quaternion w x y z). A static snapshot: it does not animate.{other_formats}

{emb}  The animatable avatar: each Gaussian embedded on the canonical mesh (format
    "meshsplat-embedding" v1, arrays little-endian base64). face [N] (triangle index),
    uv [N,2] (barycentric: P = u*V[a] + v*V[b] + (1-u-v)*V[c] for face (a,b,c); already
    includes the trained offset duv{uv_note}), d [N] (displacement along the interpolated
    vertex normal), rotation [N,4] (canonical quaternion wxyz, unnormalised), log_scale [N,3]
    (canonical log-scale), opacity_logit [N], sh0 [N,1,3] and shN [N,K,3] (colour as SH).
    meta.scale_mode says how posing scales the Gaussians: sqrt_area (by sqrt of the triangle
    area ratio), area, or none. In a pose, mean = P + d*n on the posed mesh, rotation =
    (rotation of the triangle's frame from canonical to posed) * normalize(rotation).

{mesh}  The canonical driving mesh (vertices and triangles) the embedding refers to. Drive it
    with any animation of the same mesh (same vertex order) to animate the avatar.

{shading}Load the avatar back: meshsplat.export.load_exported_avatar("<this folder>").
"""

_SHADING_README = """Shading: this avatar was trained with pose-dependent shading. In {emb}, sh0/shN are the
    ALBEDO and meta.shading holds the learned illumination: displayed rgb = albedo *
    max(0, sum_k coeffs[k] * Y_k(n)), Y_0..8 the real SH basis of order 2 (x,y,z of the unit
    normal n in world space: 0.282095; 0.488603*y, z, x; 1.092548*xy, 1.092548*yz,
    0.315392*(3z^2-1), 1.092548*xz, 0.546274*(x^2-y^2)), n = the posed Phong normal ("phong")
    or the Gaussian's shortest posed axis facing the same side ("axis"), per meta.shading.normal.
    {ply} has the shading BAKED for the canonical pose (its f_dc is albedo * E(canonical normal)).
    With meta.shading.occlusion (shading.occlusion=directions), E also holds lights from fixed
    directions shadowed by the posed mesh (see meta.shading.colour); the PLY bakes those of the
    canonical pose. shading.occlusion=key: the same with one direction, the key light, once
    meta.shading.occlusion.aligned; with soft_deg > 0 its V is the mean over directions within
    soft_deg degrees of it (an area light's soft shadow). With meta.shading.specular (shading.specular=sh2), sum_k specular.coeffs[k] * Y_k(n)
    is ADDED after the albedo multiply (not clamped); the PLY bakes it too.

"""


def canonical_gaussians(avatar: Avatar) -> tuple[ComposedGaussians, torch.Tensor]:
    """Composed Gaussians and Phong normals ``[N,3]`` of ``avatar`` in its canonical pose (no SH view term)."""
    v = avatar.mesh.vertices
    with torch.no_grad():
        # campos only feeds the view-dependent colour, which the PLY does not store (it stores SH)
        campos = torch.zeros(3, device=v.device, dtype=v.dtype) if avatar.sh_degree > 0 else None
        g = avatar.compose(v, campos=campos).detach()
        uv = effective_uv(avatar.params, avatar.clamp_to_face)
        _, normals = embed(avatar.pose(v), avatar.params["face"], uv, avatar.params["d"].detach())
    return g, normals.detach()


_FORMAT_NOTES = {
    "splat": "antimatter15 .splat: 32 bytes per Gaussian (float32 xyz and linear scale, uint8 RGBA and\n"
    "    quaternion wxyz), DC colour only, sorted by size x opacity.",
    "spz": "Niantic SPZ version 3 (gzip): quantized positions (24-bit), colours, scales, rotations and SH.",
    "gltf": "glTF 2.0 binary with KHR_gaussian_splatting (release candidate): a POINTS primitive with\n"
    "    linear scale, linear opacity, xyzw rotation, SH per degree, and a COLOR_0 fallback.",
}


def _write_splats(writer: Callable[[Path, dict[str, Any]], Path], tmp: Path, arrays: dict[str, Any]) -> Path:
    return writer(tmp, arrays)


def export_avatar(
    avatar: Avatar,
    out_dir: str | Path,
    source: str = "",
    iteration: int | None = None,
    formats: Sequence[str] = ("ply",),
) -> ExportResult:
    """Write the canonical-pose splats in ``formats`` (any of ``SPLAT_FORMATS``: ply, splat, spz, gltf),
    ``embedding.json``, ``canonical_mesh.obj`` and ``README.txt`` to ``out_dir``."""
    if not isinstance(avatar, Avatar):
        raise MeshsplatError(f"avatar: expected an Avatar, got {type(avatar).__name__}")
    formats = list(dict.fromkeys(formats))
    bad = [f for f in formats if f not in SPLAT_FORMATS]
    if bad or not formats:
        raise MeshsplatError(f"formats: expected some of {', '.join(SPLAT_FORMATS)}, got {bad or 'none'}")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    p = {k: v.detach() for k, v in avatar.params.items()}
    g, normals = canonical_gaussians(avatar)
    ply_sh0 = p["sh0"]
    if avatar.shading is not None:  # the static PLY gets the canonical pose's shading baked into its DC colour
        ply_sh0 = rgb_to_sh0(avatar.base_rgb())
    splats: dict[str, Path] = {}
    if "ply" in formats:
        splats["ply"] = write_with(
            out / PLY_NAME,
            lambda tmp: write_gaussian_ply(
                tmp,
                g.means,
                g.quats,
                g.scales.log(),
                p["opacity_logit"],
                ply_sh0,
                p.get("shN"),
                sh_degree_pad=3,
                normals=normals,
            ),
        )
    arrays: dict[str, Any] = {
        "means": g.means,
        "quats": g.quats,
        "log_scales": g.scales.log(),
        "opacity_logits": p["opacity_logit"],
        "sh0": ply_sh0.reshape(-1, 3),
        "shN": p.get("shN"),
    }
    arrays = {k: (None if v is None else v.detach().cpu().double().numpy()) for k, v in arrays.items()}
    writers = {"splat": write_splat, "spz": write_spz, "gltf": write_gltf_splats}
    for fmt in formats:
        if fmt != "ply":
            splats[fmt] = write_with(out / SPLAT_FORMATS[fmt], partial(_write_splats, writers[fmt], arrays=arrays))
    with torch.no_grad():
        uv = effective_uv(avatar.params, avatar.clamp_to_face).detach()
    emb_params = {
        "face": p["face"],
        "uv": uv,
        "d": p["d"],
        "rotation": p["rotation"],
        "log_scale": p["log_scale"],
        "opacity_logit": p["opacity_logit"],
        "sh0": p["sh0"],
    }
    if "shN" in p:
        emb_params["shN"] = p["shN"]
    meta = {
        "scale_mode": avatar.scale_mode,
        "uv_includes_duv": True,
        "uv_clamped_to_face": bool(avatar.clamp_to_face),
        "num_vertices": avatar.mesh.num_vertices,
        "num_faces": avatar.mesh.num_faces,
        "mesh": MESH_NAME,
        "source": str(source),
        "iteration": iteration,
        "color": "rgb = 0.5 + 0.28209479177387814 * sh0 (+ SH bands)",
        "opacity": "sigmoid(opacity_logit)",
        "scale": "exp(log_scale) * pose scale factor",
        "quaternion": "wxyz",
        "sh_frame": avatar.sh_frame,
        "antialiased": avatar.antialiased,
    }
    if avatar.shading is not None:
        sd = avatar.shading.json_state()
        shading_meta: dict[str, Any] = {**sd, "colour": "rgb = albedo (sh0, shN) * max(0, SH9(n) . coeffs)"}
        if "occlusion" in sd:
            shading_meta["colour"] = (
                "rgb = albedo * (max(0, SH9(n) . coeffs) + sum_k max(0, light_k) V_k max(0, n . directions_k)), "
                "V_k: the surface point lit from directions_k by the posed mesh (meshsplat.mesh.visibility)"
            )
            if sd["occlusion"].get("soft_deg"):
                shading_meta["colour"] += (
                    "; the aligned key's V: the mean of V over the directions within soft_deg of it "
                    "(meshsplat.gaussians.shading.Shading.shadow_directions)"
                )
        if "specular" in sd:
            shading_meta["colour"] += " + SH9(n) . specular.coeffs (added, not clamped)"
        meta["shading"] = shading_meta
    # every file goes to a temporary name and is renamed into place: a full disk leaves no truncated file
    emb = write_with(out / EMBEDDING_NAME, lambda tmp: write_embedding_json(tmp, emb_params, meta))
    mesh = write_with(out / MESH_NAME, lambda tmp: write_obj(tmp, avatar.mesh.vertices.detach(), avatar.mesh.faces))
    readme = out / "README.txt"
    others = "".join(
        f"\n\n{SPLAT_FORMATS[f]}  {_FORMAT_NOTES[f]} Same Gaussians as {PLY_NAME} (same axes)."
        for f in formats
        if f != "ply"
    )
    write_text_atomic(
        readme,
        _README.format(
            source=source or "(in-memory avatar)",
            n=avatar.num_gaussians,
            sh=avatar.sh_degree,
            scale_mode=avatar.scale_mode,
            clamp=", trained without walking (uv clamped to the face)" if avatar.clamp_to_face else "",
            ply=PLY_NAME,
            emb=EMBEDDING_NAME,
            mesh=MESH_NAME,
            uv_note=", projected onto the triangle" if avatar.clamp_to_face else "",
            splat_files="" if "ply" in formats else f"({PLY_NAME} was not written: --format {','.join(formats)})\n",
            other_formats=others,
            shading=_SHADING_README.format(emb=EMBEDDING_NAME, ply=PLY_NAME) if avatar.shading is not None else "",
        ),
    )
    return ExportResult(out, splats.get("ply"), emb, mesh, readme, splats)


def load_exported_avatar(
    path: str | Path, mesh_path: str | Path | None = None, device: torch.device | str = "cpu"
) -> Avatar:
    """Avatar from an export folder (or its ``embedding.json``), mesh from ``canonical_mesh.obj``."""
    path = Path(path)
    emb_path = path / EMBEDDING_NAME if path.is_dir() else path
    if not emb_path.is_file():
        raise MeshsplatError(f"no {EMBEDDING_NAME} at {path} (expected a meshsplat export folder)")
    arrays, meta = read_embedding_json(emb_path)
    obj = read_obj(Path(mesh_path) if mesh_path is not None else emb_path.parent / meta.get("mesh", MESH_NAME))
    mesh = TriMesh(obj.vertices.to(device), obj.faces.to(device))
    a = {k: v.to(device) for k, v in arrays.items()}
    shN = a.get("shN")
    params = make_params(
        a["face"],
        a["uv"],
        d=a["d"],
        log_scale=a["log_scale"],
        rotation=a["rotation"],
        opacity_logit=a["opacity_logit"],
        sh0=a["sh0"],
        shN=shN if shN is not None and shN.shape[1] > 0 else None,
    )

    shading = Shading.from_state_dict(meta.get("shading"), device)
    return Avatar(
        mesh,
        params,
        meta.get("scale_mode", "sqrt_area"),
        clamp_to_face=False,
        shading=shading,
        sh_frame=meta.get("sh_frame", "world"),
        antialiased=bool(meta.get("antialiased", False)),
    )
