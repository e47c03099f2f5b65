"""A procedural animated creature for tests and the bring-your-own-mesh check (not a shipped asset).

A striped, spotted caterpillar about 60 cm long, z-up, in centimetres: a tube along x with round
caps, a texture on a UV layout with a seam (duplicated vertices, as exported meshes have), and two
clips: ``crawl`` (a travelling body wave, the head lifting) and ``idle`` (slow breathing).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np


def _texture(size: int = 64) -> np.ndarray:
    u, v = np.meshgrid(np.linspace(0, 1, size), np.linspace(0, 1, size), indexing="xy")
    base = np.array([0.35, 0.62, 0.22])
    stripe = (np.sin(2 * math.pi * 12 * u) > 0.4)[..., None] * np.array([0.45, 0.25, -0.1])
    spot = ((np.sin(2 * math.pi * 6 * u) * np.sin(2 * math.pi * 4 * v)) > 0.75)[..., None] * np.array([0.5, 0.1, 0.4])
    belly = (np.abs(v - 0.75) < 0.12)[..., None] * np.array([0.4, 0.3, 0.2])
    img = np.clip(base + stripe + spot + belly, 0, 1)
    return (img * 255).astype(np.uint8)


def creature_rest(rings: int = 20, segments: int = 14) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(rest [V,3] cm z-up, faces [F,3], uvs [V,2], axial u [V])``; the UV seam duplicates a column."""
    length = 60.0
    verts, uvs, axial = [], [], []
    for i in range(rings):
        u = (i + 0.5) / rings
        x = (u - 0.5) * length
        r = 5.5 * math.sin(math.pi * (0.08 + 0.84 * u)) ** 0.5 + 0.8 * (u > 0.85)  # head slightly bigger
        for j in range(segments + 1):  # the last column duplicates the first (UV seam)
            a = 2 * math.pi * j / segments
            verts.append([x, r * math.cos(a), 6.5 + r * math.sin(a)])
            uvs.append([u, j / segments])
            axial.append(u)
    ring = lambda i, j: i * (segments + 1) + j  # noqa: E731
    faces = []
    for i in range(rings - 1):
        for j in range(segments):
            a, b, c, d = ring(i, j), ring(i, j + 1), ring(i + 1, j), ring(i + 1, j + 1)
            faces += [[a, c, b], [b, c, d]]
    for end, i, sign in ((0, 0, -1.0), (1, rings - 1, 1.0)):  # caps: one pole each
        pole = len(verts)
        x = verts[ring(i, 0)][0] + sign * 2.5
        verts.append([x, 0.0, 6.5])
        uvs.append([float(end), 0.5])
        axial.append(float(end))
        for j in range(segments):
            a, b = ring(i, j), ring(i, j + 1)
            faces.append([pole, b, a] if sign < 0 else [pole, a, b])
    return (
        np.asarray(verts, np.float32),
        np.asarray(faces, np.int64),
        np.asarray(uvs, np.float32),
        np.asarray(axial, np.float32),
    )


def creature_frames(frames_per_clip: int = 32, fps: float = 24.0, **mesh) -> dict:
    """The mesh-sequence ``.npz`` layout's arrays: crawl then idle, ``clip_names``/``clip_ranges``."""
    rest, faces, uvs, u = creature_rest(**mesh)
    out = []
    for k in range(frames_per_clip):  # crawl: body wave sideways and up, head lifts
        t = k / fps
        phase = 2 * math.pi * (1.5 * u - 1.2 * t)
        v = rest.copy()
        v[:, 1] += 6.0 * np.sin(phase)
        head = np.clip(u - 0.8, 0, None) / 0.2 * (0.5 + 0.5 * math.sin(3 * t))
        v[:, 2] += 3.0 * np.maximum(np.sin(phase + 1.0), 0) + 8.0 * head
        v[:, 0] += 4.0 * t
        out.append(v)
    for k in range(frames_per_clip):  # idle: breathing
        t = k / fps
        v = rest.copy()
        s = 1.0 + 0.04 * math.sin(2 * math.pi * 0.5 * t)
        v[:, 1:] = (v[:, 1:] - [0.0, 6.5]) * s + [0.0, 6.5]
        out.append(v)
    n = frames_per_clip
    return {
        "faces": faces,
        "vertices": np.stack(out).astype(np.float32),
        "uvs": uvs,
        "texture": _texture(),
        "fps": np.float32(fps),
        "up": np.str_("z"),
        "attribution": np.str_("procedural caterpillar (meshsplat tests, CC0)"),
        "clip_names": np.array(["crawl", "idle"]),
        "clip_ranges": np.array([[0, n - 1], [n, 2 * n - 1]]),
    }


def write_creature_npz(path, **kw) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez(path, **creature_frames(**kw))
    return path


def write_creature_frames(folder, frames: int = 8, with_texture: bool = True) -> Path:
    """A folder of OBJ frames (with ``vt`` per corner, so the seam is split on read) + texture.png."""
    from PIL import Image

    d = creature_frames(frames_per_clip=frames)
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    faces, uvs = d["faces"], d["uvs"]
    for k, v in enumerate(d["vertices"][:frames]):
        lines = [f"v {x:.5f} {y:.5f} {z:.5f}" for x, y, z in v] + [f"vt {a:.5f} {b:.5f}" for a, b in uvs]
        lines += [f"f {a + 1}/{a + 1} {b + 1}/{b + 1} {c + 1}/{c + 1}" for a, b, c in faces]
        (folder / f"frame_{k:03d}.obj").write_text("\n".join(lines) + "\n")
    if with_texture:
        Image.fromarray(d["texture"]).save(folder / "texture.png")
    (folder / "sequence.json").write_text('{"fps": 24, "up": "z", "attribution": "procedural caterpillar"}')
    return folder
