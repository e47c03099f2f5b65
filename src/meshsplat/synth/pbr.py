"""Path-traced ground truth (Mitsuba 3, optional extra ``[pbr]``): shadows, gloss and soft light.

The same surfaces, cameras and poses as the fast Lambert renderer of :mod:`meshsplat.synth.generate`,
lit the way a studio or a room lights a subject: a sky-like environment (bright above, dim below) and a
rectangular key light in the world-fixed light direction, strong and close enough to cast soft shadows
that move with the pose; the material is a principled BSDF (diffuse texture under a glossy lobe of
roughness ``roughness``), two-sided like the rasterizer. Images come from Mitsuba's ``scalar_rgb``
variant (its LLVM variant needs a newer libLLVM than many systems have), a box pixel filter (so alpha
is pixel coverage, as the Lambert renderer's supersampled masks) and an independent sampler seeded per
frame: the same seed renders the same image. Masks are the renderer's alpha.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
import torch
from numpy.typing import ArrayLike

from meshsplat.errors import MeshsplatError
from meshsplat.synth.raster import vertex_normals

__all__ = ["PbrSettings", "PbrRenderer", "RENDERERS", "load_mitsuba"]

RENDERERS = ("lambert", "pbr")
_VARIANT = "scalar_rgb"


@dataclass(frozen=True)
class PbrSettings:
    """Path tracer settings (recorded in the dataset manifest under ``renderer``).

    ``spp`` samples per pixel; ``seed`` the base seed (frame k renders with ``seed + k``);
    ``roughness`` of the glossy lobe; ``specular`` its strength (principled, 0.5 = index 1.5);
    ``key`` the key light's irradiance at the subject and ``sky`` the environment's radiance, both as
    the outgoing radiance of a white diffuse surface facing them; ``key_distance`` and ``key_size``
    in multiples of the subject's size (bounding-box diagonal); ``max_depth`` path length.
    """

    spp: int = 32
    seed: int = 0
    roughness: float = 0.45
    specular: float = 0.5
    key: float = 0.9
    sky: float = 0.3
    key_distance: float = 2.0
    key_size: float = 0.5
    max_depth: int = 4

    def check(self) -> None:
        if not 1 <= self.spp <= 65536:
            raise MeshsplatError(f"spp: expected 1..65536 samples per pixel, got {self.spp}")
        if not 0.0 < self.roughness <= 1.0:
            raise MeshsplatError(f"roughness: expected in (0, 1], got {self.roughness}")
        if min(self.key, self.sky, self.specular) < 0 or self.key_distance <= 0 or self.key_size <= 0:
            raise MeshsplatError("pbr settings: key, sky, specular must be >= 0 and key_distance, key_size > 0")
        if self.max_depth < 2:
            raise MeshsplatError(f"max_depth: expected >= 2 (camera, surface, light), got {self.max_depth}")

    def record(self) -> dict:
        return {"name": "pbr", "engine": "mitsuba3", "variant": _VARIANT, **asdict(self)}


def load_mitsuba() -> Any:
    """The ``mitsuba`` module set to ``scalar_rgb``; one MeshsplatError naming the extra when missing."""
    try:
        import mitsuba as mi
    except ImportError:
        raise MeshsplatError(
            "--renderer pbr needs Mitsuba 3: pip install 'meshsplat[pbr]' (or pip install mitsuba)"
        ) from None
    mi.set_variant(_VARIANT)
    mi.set_log_level(mi.LogLevel.Error)
    return mi


def _sky(sky: float, rows: int = 32) -> np.ndarray:
    """Latitude-longitude environment ``[rows, 2*rows, 3]``: bluish above, warm dim ground below."""
    elev = 0.5 * math.pi - (np.arange(rows) + 0.5) / rows * math.pi  # +pi/2 at the top row
    s = np.sin(elev)[:, None]
    above = np.array([0.85, 0.95, 1.15]) * (0.8 + 0.4 * s)
    below = np.array([1.0, 0.9, 0.75]) * (0.45 + 0.25 * (1 + s))
    col = np.where(s >= 0, above, below) * sky
    return np.repeat(col[:, None, :], 2 * rows, 1).astype(np.float32)


class PbrRenderer:
    """Renders one source's posed surface; build once per capture, :meth:`render` per frame.

    ``center [3]`` and ``size`` (world units) place the key light at ``center + light_dir *
    key_distance * size``; ``weld_group [V]`` shares normals across seam duplicates as the Lambert
    renderer does.
    """

    def __init__(
        self,
        source: Any,
        weld_group: torch.Tensor | None,
        center: ArrayLike,
        size: float,
        light_dir: ArrayLike,
        settings: PbrSettings,
        threads: int | None = None,
    ) -> None:
        settings.check()
        self.mi = load_mitsuba()
        if threads:
            import drjit as dr

            dr.set_thread_count(int(threads))
        self.source = source
        self.weld_group = weld_group
        self.settings = settings
        faces = source.faces.long()
        self.groups: list[tuple[torch.Tensor, torch.Tensor, dict]] = []  # (vertex ids, local faces, bsdf)
        for mi_idx, (base, tex) in enumerate(source.materials):
            sel = source.face_material == mi_idx
            if not bool(sel.any()):
                continue
            f = faces[sel]
            vid, local = torch.unique(f.reshape(-1), return_inverse=True)
            colors = source.vertex_colors[vid].float() * base.float()
            if tex is not None:
                if float((source.vertex_colors[vid] - 1).abs().max()) > 1e-3:
                    raise MeshsplatError(
                        f"material {mi_idx}: texture and vertex colours together are not supported by --renderer pbr"
                    )
                bitmap = self.mi.Bitmap(np.ascontiguousarray((tex * base).clamp(0, 1).numpy().astype(np.float32)))
                albedo: dict = {"type": "bitmap", "bitmap": bitmap, "raw": True, "filter_type": "bilinear"}
            else:
                albedo = {"type": "mesh_attribute", "name": "vertex_color"}
            bsdf = {
                "type": "twosided",
                "material": {
                    "type": "principled",
                    "base_color": albedo,
                    "roughness": settings.roughness,
                    "specular": settings.specular,
                },
            }
            info = {"bsdf_object": self.mi.load_dict(bsdf), "colors": colors, "textured": tex is not None}
            self.groups.append((vid, local.view(-1, 3), info))
        center = np.asarray(center, np.float64)
        ldir = np.asarray(light_dir, np.float64)
        ldir = ldir / np.linalg.norm(ldir)
        dist = settings.key_distance * size
        side = settings.key_size * size
        pos = center + ldir * dist
        # Irradiance of a small rectangle facing the subject: E = L * A / d^2; a white diffuse facing it
        # then reflects E / pi, which should equal settings.key.
        radiance = settings.key * math.pi * dist**2 / side**2
        self.lights = {
            "key": {
                "type": "rectangle",
                "to_world": self.mi.ScalarTransform4f.look_at(
                    origin=pos.tolist(), target=center.tolist(), up=_perpendicular(ldir).tolist()
                ).scale([side / 2, side / 2, 1.0]),
                "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [radiance] * 3}},
            },
            "sky": {"type": "envmap", "bitmap": self.mi.Bitmap(_sky(settings.sky))},
        }
        self.light_position = pos

    def _mesh(self, name: str, verts: np.ndarray, normals: np.ndarray, group: tuple) -> Any:
        vid, local, info = group
        mi = self.mi
        src = self.source
        props = mi.Properties()
        props["bsdf"] = info["bsdf_object"]
        m = mi.Mesh(name, len(vid), len(local), props, has_vertex_normals=True, has_vertex_texcoords=info["textured"])
        p = mi.traverse(m)
        p["vertex_positions"] = np.ascontiguousarray(verts[vid.numpy()], np.float32).ravel()
        p["faces"] = np.ascontiguousarray(local.numpy(), np.uint32).ravel()
        p["vertex_normals"] = np.ascontiguousarray(normals[vid.numpy()], np.float32).ravel()
        if info["textured"]:
            p["vertex_texcoords"] = np.ascontiguousarray(src.uvs[vid].numpy(), np.float32).ravel()
        p.update()
        if not info["textured"]:
            m.add_attribute("vertex_color", 3, np.ascontiguousarray(info["colors"].numpy(), np.float32).ravel())
        return m

    def render(
        self, verts: torch.Tensor, viewmat: np.ndarray, K: np.ndarray, width: int, height: int, frame: int = 0
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Path-trace ``verts [V,3]`` (world) seen by ``viewmat [4,4]`` (world->camera, OpenCV axes) and
        ``K [3,3]``: ``(rgb [H,W,3] premultiplied by alpha, alpha [H,W,1])``, rgb linear, unclamped."""
        mi = self.mi
        K = np.asarray(K, np.float64)
        if (
            abs(K[0, 0] - K[1, 1]) > 1e-6 * K[0, 0]
            or abs(K[0, 2] - width / 2) > 1e-6
            or abs(K[1, 2] - height / 2) > 1e-6
        ):
            raise MeshsplatError("--renderer pbr: cameras need square pixels and a centred principal point")
        v = verts.detach().float().cpu()
        n = vertex_normals(v, self.source.faces.long(), self.weld_group).numpy()
        vn = v.numpy()
        scene: dict = {"type": "scene", **self.lights}
        scene["integrator"] = {"type": "path", "max_depth": self.settings.max_depth, "hide_emitters": True}
        for k, g in enumerate(self.groups):
            scene[f"part{k}"] = self._mesh(f"part{k}", vn, n, g)
        c2w = np.linalg.inv(np.asarray(viewmat, np.float64)) @ np.diag([-1.0, -1.0, 1.0, 1.0])
        fov = math.degrees(2 * math.atan(0.5 * width / K[0, 0]))
        scene["sensor"] = {
            "type": "perspective",
            "fov": fov,
            "fov_axis": "x",
            "near_clip": 1e-3,
            "to_world": mi.ScalarTransform4f(c2w.tolist()),
            "sampler": {"type": "independent", "sample_count": self.settings.spp},
            "film": {
                "type": "hdrfilm",
                "width": width,
                "height": height,
                "pixel_format": "rgba",
                "rfilter": {"type": "box"},
                "sample_border": False,
            },
        }
        sc = mi.load_dict(scene)
        img = np.array(mi.render(sc, spp=self.settings.spp, seed=self.settings.seed + int(frame)))
        out = torch.from_numpy(np.ascontiguousarray(img, np.float32))
        return out[..., :3], out[..., 3:4].clamp(0, 1)


def _perpendicular(d: np.ndarray) -> np.ndarray:
    """A unit vector perpendicular to ``d [3]``."""
    a = np.array([0.0, 1.0, 0.0]) if abs(d[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
    p = np.cross(d, a)
    return p / np.linalg.norm(p)
