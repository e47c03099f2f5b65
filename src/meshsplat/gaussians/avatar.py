"""A trained avatar: canonical mesh + embedded Gaussian parameters, renderable in any pose.

    avatar = meshsplat.run_folder.load_avatar("runs/demo/run")   # run dir or a ckpt_*.pt file
    out = avatar.render(vertices, camera, background=torch.ones(3))   # camera: a meshsplat.Camera
    out.image  # [H,W,3] in [0,1]; out.alpha [H,W,1]; out.meta (rasterizer meta)

``Avatar.state_dict()`` is what training checkpoints store under ``"avatar"``: canonical mesh
(``vertices``, ``faces``), ``params`` (see ``meshsplat.gaussians.params``), ``scale_mode``,
``sh_degree``, ``clamp_to_face`` (True for avatars trained without walking), ``sh_frame`` and
``antialiased`` (opacity compensated for the screen-space dilation per view), ``shading`` (None, or the learned illumination's ``Shading.state_dict()``: then the SH colour is an
albedo and every render is shaded by the posed normals; with its ``occlusion`` also by the posed mesh's
shadows from fixed directions).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch

from meshsplat._checks import check_tensor
from meshsplat.camera import Camera
from meshsplat.embedding import SCALE_MODES
from meshsplat.errors import MeshsplatError
from meshsplat.gaussians.compose import SH_FRAMES, ComposedGaussians, compose
from meshsplat.gaussians.params import check_params, num_gaussians, sh0_to_rgb, sh_degree_of
from meshsplat.gaussians.shading import Shading
from meshsplat.mesh import MeshPose, TriMesh
from meshsplat.render import rasterize
from meshsplat.render.projection import antialias_compensation

__all__ = ["Avatar", "AvatarRender"]


@dataclass
class AvatarRender:
    image: torch.Tensor  # [H,W,3]
    alpha: torch.Tensor  # [H,W,1]
    meta: dict[str, Any]


class Avatar:
    """Canonical ``TriMesh`` + parameter dict + how to pose it (``scale_mode``)."""

    def __init__(
        self,
        mesh: TriMesh,
        params: dict[str, torch.Tensor],
        scale_mode: str = "sqrt_area",
        clamp_to_face: bool = False,
        shading: Shading | None = None,
        sh_frame: str = "world",
        antialiased: bool = False,
    ) -> None:
        if not isinstance(mesh, TriMesh):
            raise MeshsplatError(f"mesh: expected a TriMesh, got {type(mesh).__name__}")
        check_params(params)
        if int(params["face"].max()) >= mesh.num_faces or int(params["face"].min()) < 0:
            raise MeshsplatError(f"params['face']: indices must lie in [0, {mesh.num_faces})")
        self.mesh = mesh
        self.params = params
        self.scale_mode = scale_mode
        self.clamp_to_face = bool(clamp_to_face)
        if sh_frame not in SH_FRAMES:
            raise MeshsplatError(f"sh_frame: expected one of {SH_FRAMES}, got {sh_frame!r}")
        if shading is not None and not isinstance(shading, Shading):
            raise MeshsplatError(f"shading: expected a Shading or None, got {type(shading).__name__}")
        self.shading = shading
        self.sh_frame = sh_frame
        self.antialiased = bool(antialiased)

    # ---- properties ------------------------------------------------------------------
    @property
    def num_gaussians(self) -> int:
        return num_gaussians(self.params)

    @property
    def sh_degree(self) -> int:
        return sh_degree_of(self.params)

    @property
    def device(self) -> torch.device:
        return self.params["uv"].device

    def to(self, device: torch.device | str) -> Avatar:
        """A copy on ``device`` (parameters detached)."""
        params = {k: v.detach().to(device) for k, v in self.params.items()}
        mesh = TriMesh(self.mesh.vertices.to(device), self.mesh.faces.to(device))
        shading = None if self.shading is None else self.shading.to(device)
        return Avatar(mesh, params, self.scale_mode, self.clamp_to_face, shading, self.sh_frame, self.antialiased)

    # ---- posing and rendering --------------------------------------------------------
    def pose(self, verts_posed: torch.Tensor | MeshPose) -> MeshPose:
        """``MeshPose`` for ``verts_posed [V,3]`` (moved to the avatar's device and dtype). A ``MeshPose`` (from
        an earlier call) is returned as it is: posing costs milliseconds, so renders of one pose can share it."""
        dtype = self.params["uv"].dtype
        if isinstance(verts_posed, MeshPose):
            if verts_posed.verts.shape != self.mesh.vertices.shape or verts_posed.num_faces != self.mesh.num_faces:
                raise MeshsplatError(
                    f"pose: a MeshPose of {verts_posed.verts.shape[0]} vertices and {verts_posed.num_faces} faces, "
                    f"the avatar's mesh has {self.mesh.num_vertices} and {self.mesh.num_faces}"
                )
            if verts_posed.verts.device != self.device or verts_posed.verts.dtype != dtype:
                raise MeshsplatError(
                    f"pose: a MeshPose on {verts_posed.verts.device} in {verts_posed.verts.dtype}, the avatar is on "
                    f"{self.device} in {dtype} (make it with avatar.pose(vertices))"
                )
            return verts_posed
        check_tensor("verts_posed", verts_posed, "V,3", {"V": self.mesh.num_vertices}, dtype="float", finite=True)
        return MeshPose.from_vertices(self.mesh, verts_posed.to(device=self.device, dtype=dtype))

    def compose(
        self, verts_posed: torch.Tensor | MeshPose, campos: torch.Tensor | None = None, compiled: bool | None = None
    ) -> ComposedGaussians:
        """Gaussians (means, quats, scales, opacities, colors) in the pose ``verts_posed [V,3]`` (or its
        ``MeshPose``, see :meth:`pose`); ``compiled``: :func:`~meshsplat.gaussians.compose`'s."""
        return compose(
            self.params,
            self.pose(verts_posed),
            self.scale_mode,
            campos=campos,
            clamp_to_face=self.clamp_to_face,
            shading=self.shading,
            sh_frame=self.sh_frame,
            compiled=compiled,
        )

    def base_rgb(self, verts_posed: torch.Tensor | None = None) -> torch.Tensor:
        """View-independent colour ``[N,3]`` (SH DC band), with the shading of the pose ``verts_posed [V,3]``
        (default: the canonical pose) baked in when the avatar is shaded: for static exports and viewers
        that do not shade."""
        with torch.no_grad():
            rgb = sh0_to_rgb(self.params["sh0"].detach()).clamp_min(0.0)
            if self.shading is None:
                return rgb
            # compose without a camera colours by the DC band alone: the albedo times E (occlusion included),
            # plus the specular term
            return self.compose(self.mesh.vertices if verts_posed is None else verts_posed).colors.detach()

    def render(
        self,
        vertices: torch.Tensor | MeshPose,
        camera: Camera,
        background: torch.Tensor | None = None,
        backend: str = "auto",
    ) -> AvatarRender:
        """Render the avatar posed by ``vertices [V,3]`` (or their ``MeshPose`` from :meth:`pose`, to share the
        posing between renders of one pose) as seen by ``camera`` (a :class:`Camera`: world->camera ``viewmat``,
        ``K``, ``width``, ``height``; moved to the avatar's device and dtype) on ``background [3]``.
        ``backend="torch"``: torch's operations throughout (the reference), the composition included."""
        if not isinstance(camera, Camera):
            raise MeshsplatError(
                f"camera: expected a meshsplat.Camera, got {type(camera).__name__} (the signature is "
                "Avatar.render(vertices, camera, background=None, backend='auto'); make one with "
                "Camera(viewmat, K, width, height))"
            )
        check_tensor("camera viewmat", camera.viewmat, "4,4", dtype="float", finite=True)
        check_tensor("camera K", camera.K, "3,3", dtype="float", finite=True)
        width, height = camera.width, camera.height
        dev, dt = self.device, self.params["uv"].dtype
        viewmat = camera.viewmat.to(device=dev, dtype=dt)
        K = camera.K.to(device=dev, dtype=dt)
        campos = torch.linalg.inv(viewmat)[:3, 3] if self.sh_degree > 0 else None
        g = self.compose(vertices, campos=campos, compiled=False if backend == "torch" else None)
        bg = None
        if background is not None:
            check_tensor("background", background, "3", dtype="float")
            bg = background.to(device=dev, dtype=dt)[None]
        opacities = g.opacities
        if self.antialiased:
            opacities = (
                opacities
                * antialias_compensation(g.means, g.quats, g.scales, viewmat[None], K[None], int(width), int(height))[0]
            )
        out = rasterize(
            g.means,
            g.quats,
            g.scales,
            opacities,
            g.colors,
            viewmat[None],
            K[None],
            int(width),
            int(height),
            backgrounds=bg,
            backend=backend,
        )
        return AvatarRender(out.colors[0], out.alphas[0], out.meta)

    # ---- persistence -----------------------------------------------------------------
    def state_dict(self) -> dict[str, Any]:
        return {
            "vertices": self.mesh.vertices.detach().cpu(),
            "faces": self.mesh.faces.detach().cpu(),
            "params": {k: v.detach().cpu().clone() for k, v in self.params.items()},
            "scale_mode": self.scale_mode,
            "sh_degree": self.sh_degree,
            "clamp_to_face": self.clamp_to_face,
            "sh_frame": self.sh_frame,
            "antialiased": self.antialiased,
            "shading": None if self.shading is None else self.shading.state_dict(),
        }

    @classmethod
    def from_state_dict(cls, sd: dict[str, Any], device: torch.device | str = "cpu") -> Avatar:
        verts, faces, params = _checked_state(sd)
        mesh = TriMesh(verts.to(device), faces.to(device))
        sh_frame, antialiased = sd.get("sh_frame", "world"), sd.get("antialiased", False)
        if sh_frame not in SH_FRAMES:
            raise MeshsplatError(f"avatar sh_frame: expected one of {list(SH_FRAMES)}, got {sh_frame!r}")
        if not isinstance(antialiased, bool):
            raise MeshsplatError(f"avatar antialiased: expected true/false, got {antialiased!r}")
        try:
            shading = Shading.from_state_dict(sd.get("shading"), device)
        except (KeyError, AttributeError, TypeError, ValueError) as exc:
            raise MeshsplatError(f"avatar shading state is invalid ({exc})") from None
        return cls(
            mesh,
            {k: v.to(device) for k, v in params.items()},
            sd.get("scale_mode", "sqrt_area"),
            sd.get("clamp_to_face", False),
            shading,
            sh_frame,
            antialiased,
        )

    def __repr__(self) -> str:
        return (
            f"Avatar(N={self.num_gaussians}, mesh={self.mesh!r}, scale_mode={self.scale_mode!r}, "
            f"sh_degree={self.sh_degree}, shading={self.shading!r})"
        )


def _checked_state(sd: Any) -> tuple[torch.Tensor, torch.Tensor, dict[str, torch.Tensor]]:
    """Validate an ``Avatar.state_dict()`` read from a file: types, shapes, finiteness, index ranges.
    Returns float32 vertices, long faces and params (floats as float32, ``face`` as long)."""
    if not isinstance(sd, dict):
        raise MeshsplatError(f"avatar state: expected a dict, got {type(sd).__name__}")
    missing = [k for k in ("vertices", "faces", "params") if k not in sd]
    if missing:
        raise MeshsplatError(f"avatar state is incomplete (missing {', '.join(missing)})")
    dims: dict[str, int] = {}
    verts = check_tensor("avatar vertices", sd["vertices"], "V,3", dims, dtype="float", finite=True)
    faces = check_tensor("avatar faces", sd["faces"], "F,3", dims, dtype="int")
    if dims["V"] < 3 or dims["F"] < 1:
        raise MeshsplatError(f"avatar mesh is empty ({dims['V']} vertices, {dims['F']} faces)")
    if int(faces.min()) < 0 or int(faces.max()) >= dims["V"]:
        raise MeshsplatError(f"avatar faces: indices must lie in [0, {dims['V']})")
    params = sd["params"]
    if not isinstance(params, dict) or not all(isinstance(v, torch.Tensor) for v in params.values()):
        raise MeshsplatError("avatar params: expected a dict of tensors")
    check_params(params)
    if num_gaussians(params) == 0:
        raise MeshsplatError("avatar params hold no Gaussians")
    out = {}
    for k, v in params.items():
        if k == "face":
            out[k] = v.long()
        else:
            if not torch.isfinite(v).all():
                raise MeshsplatError(f"avatar params['{k}']: contains {int((~torch.isfinite(v)).sum())} NaN/Inf values")
            out[k] = v.float()
    if sd.get("scale_mode", "sqrt_area") not in SCALE_MODES:
        raise MeshsplatError(f"avatar scale_mode: expected one of {SCALE_MODES}, got {sd.get('scale_mode')!r}")
    if not isinstance(sd.get("clamp_to_face", False), bool):
        raise MeshsplatError(f"avatar clamp_to_face: expected true/false, got {sd.get('clamp_to_face')!r}")
    return verts.float(), faces.long(), out
