"""Animated, coloured surfaces the generator renders: glTF assets and the ICT blendshape head.

A source exposes ``faces [F,3]``, ``clips``, ``time_range(clip)``, ``pose(clip, time) -> [V,3]``,
``rest() -> [V,3]``, surface colour data (``uvs``, ``vertex_colors``, ``face_material``,
``materials`` as (base rgb [3], texture [Ht,Wt,3] float or None)) and ``derive(src, faces, rest)``
giving a re-skinned driving mesh with the same ``pose``/``rest``.
"""

from __future__ import annotations

from pathlib import Path
from typing import ClassVar, cast

import numpy as np
import torch
from numpy.typing import ArrayLike

from meshsplat.drivers.blendshape import BlendshapeDriver
from meshsplat.drivers.gltf import GltfDriver
from meshsplat.drivers.mesh_sequence import FRAMES_LAYOUT, NPZ_LAYOUT, is_mesh_sequence, read_mesh_sequence
from meshsplat.errors import MeshsplatError
from meshsplat.io.arrays import npz_keys
from meshsplat.paths import BUNDLED, resolve_input
from meshsplat.synth.body_source import MODEL_SOURCES, ModelSource, load_model_source
from meshsplat.synth.sequence_source import SequenceSource

__all__ = ["GltfSource", "BlendshapeSource", "load_source", "gltf_attribution"]

ICT_LAYOUT = "blend-shape head npz (neutral [V,3], faces [F,3], expr_deltas [K,V,3])"


def gltf_attribution(doc: object) -> str:
    """Credit line from a glTF's ``asset.copyright`` and ``asset.extras`` (title, author, license, source)."""
    asset = getattr(doc, "asset", None)
    parts = []
    extras = getattr(asset, "extras", None) or {}
    if isinstance(extras, dict):
        for key in ("title", "author", "license", "source"):
            if extras.get(key):
                parts.append(f"{key}: {extras[key]}")
    copyright_ = getattr(asset, "copyright", None)
    if copyright_:
        parts.insert(0, str(copyright_).strip())
    return "; ".join(parts)


class GltfSource:
    attribution = ""
    default_train_clip: str | None = None
    default_test_clips: list[str] | None = None

    def __init__(self, driver: GltfDriver) -> None:
        self.driver = driver
        self.faces = driver.faces
        self.uvs = driver.uvs
        self.vertex_colors = driver.vertex_colors[:, :3]
        self.face_material = driver.face_material
        self.materials = [
            (
                torch.from_numpy(m.base_color[:3].astype(np.float32)),
                None if m.texture is None else torch.from_numpy(m.texture[..., :3]).float() / 255.0,
            )
            for m in driver.materials
        ]
        self.clips = cast("list[str | None]", driver.clips or [None])

    def time_range(self, clip: str | None) -> tuple[float, float]:
        return self.driver.time_range(clip) if clip is not None else (0.0, 0.0)

    def pose(self, clip: str | None, time: float) -> torch.Tensor:
        return self.driver.vertices_at(time, clip) if clip is not None else self.driver.rest_vertices()

    def rest(self) -> torch.Tensor:
        return self.driver.rest_vertices()

    def derive(self, src: ArrayLike, faces: ArrayLike, rest: ArrayLike | None = None) -> GltfSource:
        return GltfSource(self.driver.derive(src, faces, rest))


ICT_HIDDEN_MATERIALS = ("M_EyeBlend", "M_EyeOcclusion", "M_LacrimalFluid")  # ICT's transparent eye shells


class BlendshapeSource:
    """ICT head with a procedural talking clip ``"talk"`` and a procedural skin texture."""

    attribution = "ICT FaceKit head (MIT, (c) 2020 USC Institute for Creative Technologies)"
    _HIDDEN = ICT_HIDDEN_MATERIALS
    _COLORS: ClassVar[dict[str, tuple[float, float, float]]] = {
        "M_EyeLashes": (0.08, 0.06, 0.05),
        "M_GumsTongue": (0.75, 0.35, 0.35),
        "M_IrisLeft": (0.25, 0.35, 0.55),
        "M_IrisRight": (0.25, 0.35, 0.55),
        "M_ScleraLeft": (0.92, 0.9, 0.88),
        "M_ScleraRight": (0.92, 0.9, 0.88),
        "M_Teeth": (0.93, 0.9, 0.82),
    }

    def __init__(self, driver: BlendshapeDriver, duration: float = 8.0, keep: torch.Tensor | None = None) -> None:
        self.driver = driver
        self.duration = duration
        faces = driver.faces
        names = driver.material_names
        fm = driver.face_material if driver.face_material is not None else torch.zeros(len(faces), dtype=torch.long)
        if keep is None:
            hidden = [i for i, n in enumerate(names) if n in self._HIDDEN]
            keep = ~torch.isin(fm, torch.tensor(hidden, dtype=torch.long))
        self.faces = faces[keep]
        self.face_material = fm[keep]
        self.materials = [(torch.tensor(self._COLORS.get(n, (1.0, 1.0, 1.0))), None) for n in (names or ["skin"])]
        rest = driver.neutral
        self.uvs = torch.zeros(rest.shape[0], 2)
        self.vertex_colors = self._skin_texture(rest)
        self.clips = ["talk"]

    @staticmethod
    def _skin_texture(rest: torch.Tensor) -> torch.Tensor:
        """Procedural skin: a warm tone with smooth blotches and fine stripes fixed to the rest surface."""
        p = (rest - rest.mean(0)) / (rest.max(0).values - rest.min(0).values).max()
        base = torch.tensor([0.85, 0.62, 0.50])
        blotch = torch.sin(9 * p[:, 0] + 2) * torch.sin(7 * p[:, 1] + 1) * torch.sin(8 * p[:, 2])
        fine = torch.sin(60 * p[:, 1]) * torch.sin(45 * p[:, 0] + 20 * p[:, 2])
        shade = 1 + 0.12 * blotch[:, None] + 0.06 * fine[:, None]
        return (base * shade * torch.tensor([1.0, 0.97, 0.95])).clamp(0, 1)

    def time_range(self, clip: str | None) -> tuple[float, float]:
        return 0.0, self.duration

    def pose(self, clip: str | None, time: float) -> torch.Tensor:
        w, rot = self.driver.talking_params([time])
        return self.driver.pose(w[0], rot[0])

    def rest(self) -> torch.Tensor:
        return self.driver.neutral.clone()

    def derive(self, src: ArrayLike, faces: ArrayLike, rest: ArrayLike | None = None) -> BlendshapeSource:
        src_t = torch.as_tensor(np.asarray(src), dtype=torch.long)
        rest_t = None if rest is None else torch.as_tensor(np.asarray(rest), dtype=torch.float32)
        new = self.driver.derive(src_t, np.asarray(faces), rest_t)  # keeps the head-pose pivot
        out = BlendshapeSource.__new__(BlendshapeSource)
        out.driver, out.duration, out.clips = new, self.duration, self.clips
        out.faces = new.faces
        out.face_material = torch.zeros(len(new.faces), dtype=torch.long)
        out.materials, out.uvs, out.vertex_colors = self.materials[:1], self.uvs[src_t], self.vertex_colors[src_t]
        return out


_ATTRIBUTION = {
    "cesiumman": "CesiumMan (CC-BY 4.0, (c) 2017 Cesium; Khronos glTF sample model)",
    "robotexpressive": "RobotExpressive (CC0 1.0, Tomas Laulhe / Quaternius; morph targets Don McCurdy)",
    "riggedsimple": "RiggedSimple (CC-BY 4.0, Khronos glTF sample model)",
}


def load_source(
    asset: Path | str, model_dir: Path | str | None = None, gender: str = "neutral"
) -> GltfSource | BlendshapeSource | SequenceSource | ModelSource:
    """Load ``asset``: a .glb/.gltf path, a mesh sequence (.npz with faces + vertices, or a folder of
    OBJ/PLY frames, :mod:`meshsplat.drivers.mesh_sequence`), an .npz blendshape file, a bundled asset's name
    (``CesiumMan``, ``RobotExpressive``, ``RiggedSimple``, ``ict``) or a body/head model
    (``smpl``, ``smplx``, ``flame``; files from ``model_dir`` or ``$MESHSPLAT_MODEL_DIR``)."""
    p = Path(asset)
    if not p.exists() and str(asset).lower() in MODEL_SOURCES:
        return load_model_source(str(asset).lower(), model_dir, gender)
    p = resolve_input(asset)
    if not p.exists():
        raise MeshsplatError(
            f"asset not found: {asset} (a .glb/.gltf/.npz path, a folder of OBJ/PLY frames, or one of "
            f"{', '.join(BUNDLED)}, {', '.join(MODEL_SOURCES)})"
        )
    if p.is_dir() or p.suffix.lower() in (".npz", ".npy"):
        if is_mesh_sequence(p) or p.is_dir() or p.suffix.lower() == ".npy":
            return SequenceSource(read_mesh_sequence(p), name=str(p))
        keys = sorted(npz_keys(p))
        if not {"neutral", "faces", "expr_deltas"} <= set(keys):
            raise MeshsplatError(f"{p}: keys {keys} fit no npz layout: the {NPZ_LAYOUT} or the {ICT_LAYOUT}")
        return BlendshapeSource(BlendshapeDriver.from_npz(p))
    if p.suffix.lower() not in (".glb", ".gltf"):
        raise MeshsplatError(
            f"asset: {p} is none of: a .glb/.gltf (morph or skin animation), the {NPZ_LAYOUT}, "
            f"a {FRAMES_LAYOUT}, the {ICT_LAYOUT}"
        )
    src = GltfSource(GltfDriver(p))
    src.attribution = gltf_attribution(src.driver.file.doc) or _ATTRIBUTION.get(p.stem.lower(), "")
    if p.stem.lower() == "robotexpressive":  # the demo's clip choice for the shared robot
        src.default_train_clip, src.default_test_clips = "Walking", ["Wave", "Dance"]
    return src
