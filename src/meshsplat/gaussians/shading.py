"""Pose-dependent shading: per-Gaussian albedo times a learned illumination shared by the avatar.

With shading on, a Gaussian's SH colour (``sh0``/``shN``) is its *albedo* and the displayed colour is

    colour = albedo * E(n)

where ``n [N,3]`` is the Gaussian's posed normal and ``E`` is second-order spherical-harmonic
irradiance in world space (9 coefficients per channel, ``coeffs [9,3]``; Ramamoorthi & Hanrahan's
form, the 9 real SH basis functions evaluated at ``n``). As the mesh moves, ``n`` turns with it, so
the shading follows the motion while the albedo stays fixed. ``coeffs`` starts at E = 1 (white,
uniform light) so the untrained model equals the unshaded one.

Normals (``normal``): ``"phong"`` - the interpolated vertex normal of the embedding on the posed
mesh (smooth, follows the surface); ``"axis"`` - the Gaussian's own shortest posed axis, signed to
face the same side as the Phong normal (follows the flattened splat).

Occlusion (``occlusion="directions"``): the irradiance gains a direct term that knows the posed mesh's
shadows, ``E(x, n) = E_sh2(n) + sum_k L_k V_k(x) max(0, n . w_k)``, over ``K`` fixed far directions
``w_k [K,3]`` spread over the sphere, with learned non-negative RGB intensities ``light [K,3]`` (zero at
the start, so the untrained model equals the one without occlusion) and the visibility ``V_k(x)`` of
the Gaussian's surface point from ``w_k``, computed every frame from the posed driving mesh
(``meshsplat.mesh.visibility``: a depth grid of ``grid x grid`` cells per direction; no learning, no
gradient through it).

Key light (``occlusion="key"``): the same candidate directions at first; then, in stages
(:meth:`Shading.align_key`, called by the trainer), the estimate of the key light's direction is the
mean of the strongest light and its neighbours within ``KEY_CONE_DEG``, weighted by intensity squared;
the remaining lights fold into the SH2 irradiance (their clamped-cosine lobes' SH2 projection,
unshadowed). Each of ``KEY_RINGS_DEG`` then puts a ring of ``KEY_RING`` new candidates around the
estimate (all of them sharing the merged intensity equally), to be weighted again, narrowing the
estimate; the last stage keeps one key light: one shadow map per frame,
``E(x, n) = E_sh2(n) + L V(x) max(0, n . w)``. With ``key_soft`` (an angular radius in degrees) the key
is an area light: ``V(x)`` is the mean visibility from ``KEY_SOFT_SAMPLES`` directions spread over the
disk of that radius around ``w``, so shadows soften with the occluder's distance as a studio light's do.
A key light's shadow placed within a few degrees of the true light is what moves with pose; the fixed
directions are tens of degrees off, which is why their shadows transfer badly.

Seeded search (``align_key(start=...)`` at the first stage; the trainer's ``shading.key_seed``): the start
of the rings is given instead of taken from the strongest candidate; :meth:`Shading.key_seed` is the
direction of the learned irradiance itself, the SH2 coefficients plus every candidate's lobe unshadowed
(:func:`irradiance_direction`: where a clamped-cosine lobe fits it best), which points at the light
wherever the light is, while the strongest shadowed candidate may be the one whose shadows happen to fit.
A seeded first stage keeps the unshadowed irradiance: every candidate folds into the SH2 coefficients and
the ring's lobes are taken out of them again, so only the shadows change (two starts compare fairly).
:meth:`Shading.move_key` moves an aligned key to another direction with the unshadowed irradiance kept
(the trainer's ``shading.key_snap_deg`` moves it to the irradiance's own direction where the two disagree).
:meth:`Shading.drop_key` folds the key light into the SH2 irradiance (``occlusion="none"`` from then on,
its direction kept in ``dropped_key`` for readers): the trainer's ``shading.key_check_frames`` does so when
the key's shadow does not lower the error of a few training frames.

Specular (``specular="sh2"``): light that is ADDED rather than albedo-multiplied, ``S(n) = SH9(n) . spec``
with learned ``specular [9,3]`` (zero at the start, so the untrained model equals the one without it):

    colour = albedo * E(n) + S(n)

A glossy highlight on a coloured surface (white on a blue stripe) is such added light; ``albedo * E``
alone cannot make it. ``S`` is not clamped (it may also darken where the albedo overshoots).
"""

from __future__ import annotations

import math
from typing import Any

import torch

from meshsplat._numba import numba_available
from meshsplat._typing import Device
from meshsplat.errors import MeshsplatError
from meshsplat.gaussians._shading_numba import irradiance_compiled
from meshsplat.mesh.pose import MeshPose
from meshsplat.mesh.quaternion import quat_to_matrix
from meshsplat.mesh.visibility import sphere_directions

__all__ = [
    "Shading",
    "SHADING_MODES",
    "SHADING_NORMALS",
    "OCCLUSION_MODES",
    "SPECULAR_MODES",
    "sh9_basis",
    "shading_normals",
    "irradiance_direction",
]

SHADING_MODES = ("none", "sh2")  # model.shading: off (the paper) | the learned SH irradiance of this module
SHADING_NORMALS = ("phong", "axis")
# shading.occlusion: off | lights from fixed directions, shadowed by the mesh | one key light found among them
OCCLUSION_MODES = ("none", "directions", "key")
KEY_CONE_DEG = 70.0  # align_key: candidate lights this close to the strongest one merge into the key
KEY_RINGS_DEG = (25.0, 10.0)  # align_key: the rings of new candidates around the estimate, stage by stage
KEY_RING = 6  # candidates per ring
KEY_STAGES = 1 + len(KEY_RINGS_DEG)  # align_key calls until one key light is left
KEY_SOFT_SAMPLES = 12  # key_soft > 0: shadow-map directions spread over the key light's disk
# the clamped cosine max(0, n . w) in SH2: A_l * Y_lm(w) per band l (Ramamoorthi & Hanrahan)
_CLAMPED_COS_BANDS = (math.pi, 2 * math.pi / 3, 2 * math.pi / 3, 2 * math.pi / 3) + (math.pi / 4,) * 5
SEED_SEARCH = 4096  # irradiance_direction: the directions scored at first (about 3.2 degrees apart)
SEED_RINGS_DEG = (2.0, 1.0, 0.5, 0.25)  # then rings of 8 around the best, narrowing
SPECULAR_MODES = ("none", "sh2")  # shading.specular: off | an added (not albedo-multiplied) SH2 term of the normal
_Y00 = 0.28209479177387814


def sh9_basis(n: torch.Tensor) -> torch.Tensor:
    """Real SH basis up to order 2 at unit directions ``n [N,3]`` -> ``[N,9]``."""
    x, y, z = n.unbind(-1)
    return torch.stack(
        [
            torch.full_like(x, _Y00),
            0.4886025119029199 * y,
            0.4886025119029199 * z,
            0.4886025119029199 * x,
            1.0925484305920792 * x * y,
            1.0925484305920792 * y * z,
            0.31539156525252005 * (3 * z * z - 1),
            1.0925484305920792 * x * z,
            0.5462742152960396 * (x * x - y * y),
        ],
        dim=-1,
    )


def _lobes(dirs: torch.Tensor) -> torch.Tensor:
    """The SH2 projections ``[K,9]`` of the clamped cosines ``max(0, n . w_k)`` of unit ``dirs [K,3]``."""
    return sh9_basis(dirs) * torch.tensor(_CLAMPED_COS_BANDS).to(dirs)


def irradiance_direction(coeffs: torch.Tensor) -> torch.Tensor:
    """The unit direction ``w [3]`` whose clamped-cosine lobe fits the SH2 irradiance ``coeffs [9,3]`` (mean over
    RGB) best: the maximum over the sphere of ``sum_i A_i Y_i(w) c_i`` (its projection on the lobe; the linear
    band points along the light, the quadratic band sharpens it). A ``SEED_SEARCH``-direction Fibonacci sphere,
    then rings narrowing on the best (``SEED_RINGS_DEG``), in float64. A uniform irradiance gives the first
    direction of the sphere."""
    c = coeffs.detach().double().cpu().mean(-1)  # [9]
    dirs = sphere_directions(SEED_SEARCH, torch.float64, "cpu")
    best = dirs[int((_lobes(dirs) @ c).argmax())]
    for deg in SEED_RINGS_DEG:
        cand = torch.cat([best[None], _ring(best, deg, 8)])
        best = cand[int((_lobes(cand) @ c).argmax())]
    return (best / best.norm()).to(coeffs)


def shading_normals(kind: str, phong: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor) -> torch.Tensor:
    """Unit normals ``[N,3]``: the Phong normal, or the shortest Gaussian axis facing its side."""
    if kind == "phong":
        return phong
    if kind != "axis":
        raise MeshsplatError(f"shading normal: expected one of {SHADING_NORMALS}, got {kind!r}")
    rot = quat_to_matrix(quats)  # [N,3,3], columns = axes
    idx = scales.detach().argmin(-1)
    axis = rot.gather(-1, idx.view(-1, 1, 1).expand(-1, 3, 1))[..., 0]
    sign = torch.where((axis * phong).sum(-1, keepdim=True) < 0, -1.0, 1.0).to(axis.dtype)
    return axis * sign


class Shading:
    """Learned illumination ``coeffs [9,3]`` (world-space SH irradiance) and which normal it shades; with
    ``occlusion="directions"`` also ``light [K,3]`` from the fixed ``directions [K,3]``, shadowed by the
    posed mesh (visibility on a ``grid x grid`` depth grid per direction); with ``specular="sh2"`` also the
    added ``specular [9,3]`` (colour = albedo * E(n) + SH9(n) . specular)."""

    def __init__(
        self,
        coeffs: torch.Tensor | None = None,
        normal: str = "phong",
        device: Device | None = None,
        dtype: torch.dtype = torch.float32,
        *,
        occlusion: str = "none",
        directions: int = 16,
        grid: int = 64,
        light: torch.Tensor | None = None,
        key: torch.Tensor | None = None,
        key_stage: int = 0,
        specular: str = "none",
        specular_coeffs: torch.Tensor | None = None,
        key_soft: float = 0.0,
        dropped_key: torch.Tensor | None = None,
    ) -> None:
        if normal not in SHADING_NORMALS:
            raise MeshsplatError(f"shading normal: expected one of {SHADING_NORMALS}, got {normal!r}")
        if coeffs is None:
            coeffs = torch.zeros(9, 3, device=device, dtype=dtype)
            coeffs[0] = 1.0 / _Y00  # E(n) = 1 everywhere
        if not isinstance(coeffs, torch.Tensor) or tuple(coeffs.shape) != (9, 3) or not coeffs.is_floating_point():
            raise MeshsplatError("shading coeffs: expected a float tensor of shape [9, 3]")
        if not bool(torch.isfinite(coeffs).all()):
            raise MeshsplatError("shading coeffs: contain NaN or infinity")
        self.coeffs = coeffs
        self.normal = normal
        if occlusion not in OCCLUSION_MODES:
            raise MeshsplatError(f"shading occlusion: expected one of {OCCLUSION_MODES}, got {occlusion!r}")
        self.occlusion = occlusion
        self.directions: torch.Tensor | None = None
        self.light: torch.Tensor | None = None
        self.grid = int(grid)
        self.candidates = int(directions) if isinstance(directions, int) else 0  # "key": the first candidates
        if (key is not None or key_stage) and occlusion != "key":
            raise MeshsplatError("shading key: key directions given but occlusion is not 'key'")
        if not isinstance(key_stage, int) or not 0 <= key_stage <= KEY_STAGES or (key is None) != (key_stage == 0):
            raise MeshsplatError(
                f"shading key: stage 0 has no key directions, stages 1..{KEY_STAGES} have; got {key_stage!r}"
            )
        self.key_stage = key_stage
        if not isinstance(key_soft, (int, float)) or not 0.0 <= float(key_soft) <= 45.0:
            raise MeshsplatError(f"shading key_soft: expected an angular radius in 0..45 degrees, got {key_soft!r}")
        if key_soft and occlusion != "key":
            raise MeshsplatError("shading key_soft: a soft key light needs occlusion='key'")
        self.key_soft = float(key_soft)
        if dropped_key is not None:
            d = dropped_key
            if occlusion != "none" or not isinstance(d, torch.Tensor) or tuple(d.shape) != (3,):
                raise MeshsplatError("shading dropped_key: a direction [3] of a key folded away (occlusion 'none')")
            if not bool(torch.isfinite(d).all()) or abs(float(d.norm()) - 1.0) > 1e-3:
                raise MeshsplatError("shading dropped_key: expected a finite unit direction")
        # the key light's direction when drop_key folded it into coeffs (for readers; it shades nothing)
        self.dropped_key = None if dropped_key is None else dropped_key.detach().to(coeffs)
        if occlusion != "none":
            if not isinstance(directions, int) or not 1 <= directions <= 256:
                raise MeshsplatError(f"shading occlusion directions: expected 1..256, got {directions!r}")
            if not isinstance(grid, int) or not 8 <= grid <= 1024:
                raise MeshsplatError(f"shading occlusion grid: expected 8..1024 cells, got {grid!r}")
            self.directions = sphere_directions(directions, coeffs.dtype, coeffs.device)
            if key is not None:
                m = 1 if key_stage == KEY_STAGES else 1 + KEY_RING
                if (
                    not isinstance(key, torch.Tensor)
                    or tuple(key.shape) != (m, 3)
                    or not bool(torch.isfinite(key).all())
                ):
                    raise MeshsplatError(f"shading key: stage {key_stage} expects finite directions of shape [{m}, 3]")
                if float((key.norm(dim=-1) - 1.0).abs().max()) > 1e-3:
                    raise MeshsplatError("shading key: expected unit directions")
                self.directions = key.to(coeffs)
            k = int(self.directions.shape[0])
            if light is None:
                light = torch.zeros(k, 3, dtype=coeffs.dtype, device=coeffs.device)
            if not isinstance(light, torch.Tensor) or tuple(light.shape) != (k, 3):
                raise MeshsplatError(f"shading light: expected a float tensor of shape [{k}, 3]")
            if not bool(torch.isfinite(light).all()):
                raise MeshsplatError("shading light: contains NaN or infinity")
            self.light = light
        if specular not in SPECULAR_MODES:
            raise MeshsplatError(f"shading specular: expected one of {SPECULAR_MODES}, got {specular!r}")
        self.specular_mode = specular
        self.specular: torch.Tensor | None = None
        if specular == "sh2":
            if specular_coeffs is None:
                specular_coeffs = torch.zeros(9, 3, dtype=coeffs.dtype, device=coeffs.device)
            s = specular_coeffs
            if not isinstance(s, torch.Tensor) or tuple(s.shape) != (9, 3) or not s.is_floating_point():
                raise MeshsplatError("shading specular: expected a float tensor of shape [9, 3]")
            if not bool(torch.isfinite(s).all()):
                raise MeshsplatError("shading specular: contains NaN or infinity")
            self.specular = s
        elif specular_coeffs is not None:
            raise MeshsplatError("shading specular: coefficients given but specular is 'none'")

    def parameters(self) -> list[torch.Tensor]:
        """The learned tensors: ``coeffs``, with occlusion ``light``, with specular ``specular``."""
        out = [self.coeffs]
        if self.light is not None:
            out.append(self.light)
        if self.specular is not None:
            out.append(self.specular)
        return out

    @torch.no_grad()
    def project(self) -> None:
        """Keep the learned light intensities non-negative (after an optimizer step)."""
        if self.light is not None:
            self.light.clamp_(min=0.0)

    @property
    def key_aligned(self) -> bool:
        """``occlusion="key"``: one key light is left (the last stage)."""
        return self.key_stage == KEY_STAGES

    def _near_strongest(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """``(directions [K,3], intensities [K,3] >= 0, strongest's neighbours within KEY_CONE_DEG [K] bool,
        their intensity-squared weighted mean direction [3])``: the rule of ``align_key``."""
        assert self.directions is not None and self.light is not None
        dirs, light = self.directions.detach(), self.light.detach().clamp_min(0.0)
        weight = light.mean(-1)  # [K]
        strongest = dirs[int(weight.argmax())]
        near = dirs @ strongest >= math.cos(math.radians(KEY_CONE_DEG))  # [K]
        w = (weight[near, None] ** 2 * dirs[near]).sum(0)  # squared: the best-fitting candidates lead
        return dirs, light, near, strongest if float(w.norm()) < 1e-12 else w / w.norm()

    def key_estimate(self) -> torch.Tensor:
        """``occlusion="key"``, not aligned: the direction ``[3]`` the next ``align_key()`` centres on."""
        self._check_key("key_estimate")
        return self._near_strongest()[3].clone()

    def unshadowed_coeffs(self) -> torch.Tensor:
        """``[9,3]``: the SH2 irradiance with every light's clamped-cosine lobe added, unshadowed."""
        c = self.coeffs.detach()
        if self.light is None or self.directions is None:
            return c.clone()
        return c + _lobes(self.directions.detach()).T @ self.light.detach().clamp_min(0.0)

    def key_seed(self) -> torch.Tensor:
        """The learned light's direction ``[3]``: :func:`irradiance_direction` of ``unshadowed_coeffs``."""
        return irradiance_direction(self.unshadowed_coeffs())

    def _check_key(self, what: str) -> None:
        if self.occlusion != "key" or self.key_aligned:
            raise MeshsplatError(f"{what}: only a Shading with occlusion='key' that is not aligned yet")

    @torch.no_grad()
    def align_key(self, start: torch.Tensor | None = None) -> None:
        """``occlusion="key"``: the next stage; the candidate lights collapse into the key's estimate.

        The estimate is the mean of the strongest light's direction and its neighbours' within
        ``KEY_CONE_DEG``, weighted by intensity (mean over RGB) squared, carrying their summed intensity;
        every other light is folded into ``coeffs`` (its clamped-cosine lobe's SH2 projection, now
        unshadowed). Then the estimate and a ring of candidates around it (``KEY_RINGS_DEG``) share that
        intensity equally, or, at the last stage, the key alone holds it. With no light learned yet the
        strongest is the first direction, at zero intensity. In place; the tensors are new (an optimizer
        of the old ones must be rebuilt).

        ``start`` (unit ``[3]``, first stage only, e.g. ``key_seed()``): the ring is centred there instead,
        sharing the same summed intensity, and the unshadowed irradiance is kept: every candidate folds into
        ``coeffs`` and the new candidates' lobes are taken out of it."""
        self._check_key("align_key")
        dirs, light, near, key = self._near_strongest()
        merged = light[near].sum(0, keepdim=True)  # [1,3]
        if start is not None:
            if self.key_stage != 0 or not isinstance(start, torch.Tensor) or tuple(start.shape) != (3,):
                raise MeshsplatError("align_key: a start direction [3] is for the first stage only")
            key = torch.nn.functional.normalize(start.detach().to(dirs), dim=0)
            cand = torch.cat([key[None], _ring(key, KEY_RINGS_DEG[0], KEY_RING)])
            share = merged.expand(1 + KEY_RING, 3) / (1 + KEY_RING)
            self.coeffs = self.coeffs.detach() + _lobes(dirs).T @ light - _lobes(cand).T @ share
            self.key_stage = 1
            self.directions, self.light = cand, share.clone()
            return
        self.coeffs = self.coeffs.detach() + _lobes(dirs[~near]).T @ light[~near]
        self.key_stage += 1
        if self.key_aligned:
            self.directions, self.light = key[None].clone(), merged
            return
        self.directions = torch.cat([key[None], _ring(key, KEY_RINGS_DEG[self.key_stage - 1], KEY_RING)])
        self.light = merged.expand(1 + KEY_RING, 3) / (1 + KEY_RING)  # no candidate favoured at the start

    @torch.no_grad()
    def move_key(self, direction: torch.Tensor) -> None:
        """An aligned key light moves to unit ``direction [3]`` with its intensity; its old lobe folds into
        ``coeffs`` and the new one is taken out of them, so the unshadowed irradiance is unchanged and only the
        shadow moves. In place; the tensors are new (an optimizer of the old ones must be rebuilt)."""
        if self.occlusion != "key" or not self.key_aligned or self.directions is None or self.light is None:
            raise MeshsplatError("move_key: only a Shading with an aligned key light (occlusion='key')")
        if (
            not isinstance(direction, torch.Tensor)
            or tuple(direction.shape) != (3,)
            or not bool(torch.isfinite(direction).all() and direction.norm() > 0)
        ):
            raise MeshsplatError("move_key: expected a finite, non-zero direction of shape [3]")
        new = torch.nn.functional.normalize(direction.detach().to(self.directions), dim=0)[None]  # [1,3]
        light = self.light.detach().clamp_min(0.0)
        self.coeffs = self.coeffs.detach() + (_lobes(self.directions.detach()) - _lobes(new)).T @ light
        self.directions, self.light = new, light.clone()

    @torch.no_grad()
    def drop_key(self) -> None:
        """``occlusion="key"`` (any stage): fold every light into ``coeffs`` (its lobe, unshadowed) and shade
        without occlusion from then on; ``dropped_key`` keeps the direction the key had (aligned) or would
        have had. In place; the tensors are new."""
        if self.occlusion != "key" or self.directions is None or self.light is None:
            raise MeshsplatError("drop_key: only a Shading with occlusion='key'")
        key = self.directions[0] if self.key_aligned else self._near_strongest()[3]
        self.coeffs = self.unshadowed_coeffs()
        self.dropped_key = torch.nn.functional.normalize(key.detach().clone(), dim=0)
        self.occlusion, self.directions, self.light = "none", None, None
        self.key_stage, self.key_soft = 0, 0.0

    def visibility(self, pose: MeshPose, points: torch.Tensor, normals: torch.Tensor) -> torch.Tensor | None:
        """``V [N,K]`` of surface ``points [N,3]`` (unit ``normals [N,3]``) on the posed mesh ``pose``; None
        without occlusion. The pose keeps its shadow maps for the next call with the same lights."""
        if self.directions is None:
            return None
        dirs = self.shadow_directions()
        assert dirs is not None
        v = pose.shadow_maps(dirs.to(pose.verts), self.grid).lit(points, normals)
        return v.mean(-1, keepdim=True) if self.soft_key else v

    @property
    def soft_key(self) -> bool:
        """An aligned key light with an angular radius (``key_soft`` > 0): an area light, its shadow the mean
        of ``KEY_SOFT_SAMPLES`` shadow maps."""
        return self.key_aligned and self.key_soft > 0.0

    def shadow_directions(self) -> torch.Tensor | None:
        """The directions ``[K,3]`` whose shadow maps ``visibility`` builds: the lights' own, or for a soft key
        the ``KEY_SOFT_SAMPLES`` directions over its disk (float64, as the web player reads them); None
        without occlusion."""
        if self.directions is None:
            return None
        if self.soft_key:
            return _disk(self.directions[0].double(), self.key_soft, KEY_SOFT_SAMPLES)
        return self.directions

    def irradiance(
        self, normals: torch.Tensor, visible: torch.Tensor | None = None, compiled: bool | None = None
    ) -> torch.Tensor:
        """``E(n) [N,3]`` (the SH2 part clamped at 0) for unit ``normals [N,3]``, plus the shadowed directional
        light when ``visible [N,K]`` (from ``visibility``) is given. ``compiled``: by numba's kernels
        (``gaussians._shading_numba``, the same values to rounding); default: on CPU when numba is available."""
        lights = self.light is not None and self.directions is not None
        if lights and visible is None:
            raise MeshsplatError("shading with occlusion: the visibility of the posed mesh is needed")
        if compiled is None:
            compiled = normals.device.type == "cpu" and self.coeffs.device.type == "cpu" and numba_available()
        if compiled:
            if not lights:
                return irradiance_compiled(normals, self.coeffs)
            assert self.light is not None and self.directions is not None and visible is not None
            return irradiance_compiled(normals, self.coeffs, self.directions, self.light, visible)
        e = (sh9_basis(normals) @ self.coeffs.to(normals)).clamp_min(0.0)
        if not lights:
            return e
        assert self.light is not None and self.directions is not None and visible is not None
        cos = (normals @ self.directions.to(normals).T).clamp_min(0.0)  # [N,K]
        return e + (visible.to(normals) * cos) @ self.light.to(normals).clamp_min(0.0)

    def shade(
        self,
        albedo: torch.Tensor,
        phong: torch.Tensor,
        quats: torch.Tensor,
        scales: torch.Tensor,
        visible: torch.Tensor | None = None,
        compiled: bool | None = None,
    ) -> torch.Tensor:
        """Displayed colour ``[N,3]`` = albedo * E(normal) (``visible [N,K]``: with occlusion), plus the
        specular term SH9(normal) . specular when on. ``compiled``: :meth:`irradiance`'s."""
        n = shading_normals(self.normal, phong, quats, scales)
        colour = albedo * self.irradiance(n, visible, compiled)
        if self.specular is None:
            return colour
        return colour + sh9_basis(n) @ self.specular.to(n)

    def to(self, device: Device) -> Shading:
        light = None if self.light is None else self.light.detach().to(device)
        spec = None if self.specular is None else self.specular.detach().to(device)
        return Shading(
            self.coeffs.detach().to(device),
            self.normal,
            **self._occlusion_args(device),
            light=light,
            specular=self.specular_mode,
            specular_coeffs=spec,
            key_soft=self.key_soft,
            dropped_key=None if self.dropped_key is None else self.dropped_key.detach().to(device),
        )

    def _occlusion_args(self, device: Device = "cpu") -> dict[str, Any]:
        if self.directions is None:
            return {"occlusion": self.occlusion, "directions": 16, "grid": self.grid}
        if self.occlusion != "key" or self.key_stage == 0:
            return {"occlusion": self.occlusion, "directions": int(self.directions.shape[0]), "grid": self.grid}
        key = self.directions.detach().to(device)
        return {
            "occlusion": "key",
            "directions": self.candidates,
            "grid": self.grid,
            "key": key,
            "key_stage": self.key_stage,
        }

    def state_dict(self) -> dict[str, Any]:
        sd: dict[str, Any] = {
            "coeffs": self.coeffs.detach().cpu().clone(),
            "normal": self.normal,
            "space": "world",
            "order": 2,
        }
        if self.light is not None and self.directions is not None:
            sd["occlusion"] = {
                "kind": self.occlusion,
                "directions": self.directions.detach().cpu().clone(),
                "grid": self.grid,
                "light": self.light.detach().cpu().clone(),
            }
            if self.occlusion == "key":
                sd["occlusion"]["soft_deg"] = self.key_soft
                sd["occlusion"]["candidates"] = self.candidates
                sd["occlusion"]["stage"] = self.key_stage
                sd["occlusion"]["aligned"] = self.key_aligned  # for readers: one key light
        if self.specular is not None:
            sd["specular"] = {"kind": self.specular_mode, "coeffs": self.specular.detach().cpu().clone()}
        if self.dropped_key is not None:  # a key light folded into coeffs: where it was (it shades nothing)
            sd["dropped_key"] = {"direction": self.dropped_key.detach().cpu().clone()}
        return sd

    def json_state(self) -> dict[str, Any]:
        """``state_dict`` with every tensor as nested lists: the form an export's JSON holds, read back by
        ``from_state_dict`` (one serialization for checkpoints and exports)."""

        def plain(v: Any) -> Any:
            if isinstance(v, torch.Tensor):
                return v.tolist()
            return {k: plain(x) for k, x in v.items()} if isinstance(v, dict) else v

        return plain(self.state_dict())

    @classmethod
    def from_state_dict(cls, sd: dict[str, Any] | None, device: Device = "cpu") -> Shading | None:
        if sd is None:
            return None
        if not isinstance(sd, dict) or "coeffs" not in sd or not isinstance(sd.get("normal"), str):
            raise MeshsplatError("shading state: expected a dict with coeffs [9,3] and normal (phong|axis)")
        c = _float_array("coeffs", sd["coeffs"])
        if tuple(c.shape) != (9, 3) or not bool(torch.isfinite(c).all()):
            raise MeshsplatError(f"shading state: coeffs must be finite numbers [9,3], got shape {list(c.shape)}")
        spec_kw = _specular_state(sd.get("specular"), device)  # absent in states written before specular existed
        occ = sd.get("occlusion")  # absent in states written before occlusion existed
        if occ is None:
            return cls(c.to(device), sd["normal"], dropped_key=_dropped_key(sd.get("dropped_key"), device), **spec_kw)
        if (
            not isinstance(occ, dict)
            or occ.get("kind") not in OCCLUSION_MODES[1:]
            or not isinstance(occ.get("grid"), int)
        ):
            raise MeshsplatError("shading state: occlusion must hold kind (directions), directions, grid and light")
        dirs, light = (
            _float_array("occlusion directions", occ.get("directions")),
            _float_array("light", occ.get("light")),
        )
        k = int(dirs.shape[0]) if dirs.ndim == 2 else -1
        if k < 1 or tuple(dirs.shape) != (k, 3) or tuple(light.shape) != (k, 3):
            raise MeshsplatError("shading state: occlusion directions and light must both be [K,3]")
        key, stage = None, 0
        if occ["kind"] == "key":
            st, cand = occ.get("stage"), occ.get("candidates")
            if not isinstance(st, int) or not isinstance(cand, int) or not 0 <= st <= KEY_STAGES:
                raise MeshsplatError(f"shading state: a key occlusion holds its stage (0..{KEY_STAGES}) and candidates")
            stage, k = st, cand
            if stage == 0 and dirs.shape[0] != k:
                raise MeshsplatError(f"shading state: a key occlusion at stage 0 holds its {k} candidates")
            key = dirs if stage else None
        if key is None and not torch.allclose(dirs, sphere_directions(k), atol=1e-5):
            raise MeshsplatError(f"shading state: occlusion directions are not the {k} directions this version uses")
        soft = occ.get("soft_deg", 0.0)  # absent in states written before soft key shadows existed
        if not isinstance(soft, (int, float)):
            raise MeshsplatError("shading state: occlusion soft_deg must be a number")
        return cls(
            c.to(device),
            sd["normal"],
            key_soft=float(soft),
            occlusion=occ["kind"],
            directions=k,
            grid=occ["grid"],
            light=light.to(device),
            key=None if key is None else key.to(device),
            key_stage=stage,
            **spec_kw,
        )

    def __repr__(self) -> str:
        occ = "" if self.light is None else f", occlusion={self.occlusion!r} x{self.light.shape[0]}"
        occ += "" if self.dropped_key is None else ", key dropped"
        spec = "" if self.specular is None else f", specular={self.specular_mode!r}"
        return f"Shading(normal={self.normal!r}, ambient={(self.coeffs[0] * _Y00).tolist()}{occ}{spec})"


def _tangents(centre: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Unit ``a, b [3]`` completing the unit ``centre [3]`` to an orthonormal frame (helper +x, or +y near x)."""
    helper = torch.tensor([1.0, 0.0, 0.0]) if abs(float(centre[0])) < 0.9 else torch.tensor([0.0, 1.0, 0.0])
    a = torch.nn.functional.normalize(torch.linalg.cross(helper.to(centre), centre), dim=0)
    return a, torch.linalg.cross(centre, a)


def _ring(centre: torch.Tensor, degrees: float, m: int) -> torch.Tensor:
    """``m`` unit directions ``[m,3]`` at ``degrees`` from the unit ``centre [3]``, evenly around it."""
    a, b = _tangents(centre)
    phi = torch.arange(m).to(centre) * (2 * math.pi / m)
    t = math.radians(degrees)
    return math.cos(t) * centre + math.sin(t) * (phi.cos()[:, None] * a + phi.sin()[:, None] * b)


def _disk(centre: torch.Tensor, degrees: float, m: int) -> torch.Tensor:
    """``m`` unit directions ``[m,3]`` spread evenly over the cone of half-angle ``degrees`` around the unit
    ``centre [3]`` (a Vogel spiral on the tangent disk)."""
    a, b = _tangents(centre)
    i = torch.arange(m).to(centre) + 0.5
    r = (i / m).sqrt() * math.tan(math.radians(degrees))
    phi = i * (math.pi * (3.0 - math.sqrt(5.0)))
    d = centre + r[:, None] * (phi.cos()[:, None] * a + phi.sin()[:, None] * b)
    return torch.nn.functional.normalize(d, dim=-1)


def _dropped_key(entry: Any, device: Device) -> torch.Tensor | None:
    """A state's ``dropped_key`` entry (absent: None) as the direction [3]."""
    if entry is None:
        return None
    if not isinstance(entry, dict) or "direction" not in entry:
        raise MeshsplatError("shading state: dropped_key must hold direction [3]")
    d = _float_array("dropped_key direction", entry["direction"])
    if tuple(d.shape) != (3,) or not bool(torch.isfinite(d).all()):
        raise MeshsplatError("shading state: dropped_key direction must be 3 finite numbers")
    return d.to(device)


def _specular_state(spec: Any, device: Device) -> dict[str, Any]:
    """Keyword arguments of ``Shading`` from a state's ``specular`` entry (None: off)."""
    if spec is None:
        return {}
    if not isinstance(spec, dict) or spec.get("kind") not in SPECULAR_MODES[1:] or "coeffs" not in spec:
        raise MeshsplatError("shading state: specular must hold kind (sh2) and coeffs [9,3]")
    s = _float_array("specular coeffs", spec["coeffs"])
    if tuple(s.shape) != (9, 3) or not bool(torch.isfinite(s).all()):
        raise MeshsplatError(f"shading state: specular coeffs must be finite numbers [9,3], got shape {list(s.shape)}")
    return {"specular": spec["kind"], "specular_coeffs": s.to(device)}


def _float_array(name: str, value: Any) -> torch.Tensor:
    """A float32 CPU tensor from a tensor (checkpoint) or nested lists (embedding JSON)."""
    try:
        v = value.detach().cpu() if isinstance(value, torch.Tensor) else value
        return torch.as_tensor(v, dtype=torch.float32)
    except (TypeError, ValueError, RuntimeError):
        raise MeshsplatError(f"shading state: {name} must be numbers, got {type(value).__name__}") from None
