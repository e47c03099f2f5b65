"""Cameras: the one home of meshsplat's camera convention and of converters from other conventions.

Inside meshsplat a camera is a world->camera ``viewmat [4,4]`` in OpenCV axes (x right, y down,
z forward) and a pinhole ``K [3,3]`` with pixel centres at +0.5. Captures arrive in other
conventions; convert them here, once.

Pixel centres (``PIXEL_CENTER``): meshsplat's ``K`` maps the centre of the pixel in column ``i``, row
``j`` to ``(i + 0.5, j + 0.5)``; the image spans ``[0, W] x [0, H]``. This is what the rasterizer
samples (``meshsplat.render`` and gsplat evaluate pixel ``(i, j)`` at ``(i + 0.5, j + 0.5)``), what
instant-ngp / torch-ngp cast their rays through and what an OpenGL/nvdiffrast projection built from
``K`` as ``2 u / W - 1`` gives. OpenCV, and the tools that cast rays through integer pixel coordinates
(InstantAvatar, IMavatar), put pixel centres at integers: their ``cx, cy`` are 0.5 smaller for the same
camera. :func:`K_from_integer_centers` / :func:`K_to_integer_centers` convert; each capture reader
applies the convention of the tool that produced its fits (docs/formats/).

- OpenGL / Blender / NeRF / instant-ngp / VHAP ``transform_matrix``: camera->world with the camera
  looking down -z and y up -> :func:`viewmat_from_opengl_c2w`.
- Intrinsics normalised by the image size (IMavatar/DECA ``[fx/W, fy/H, cx/W, cy/H]``, fx stored
  negative) -> :func:`K_from_normalized`.
- Rodrigues vector + translation (PeopleSnapshot ``camera.pkl``) -> :func:`viewmat_from_rodrigues`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from meshsplat._checks import check_tensor
from meshsplat._typing import ArrayLike
from meshsplat.errors import MeshsplatError

__all__ = [
    "Camera",
    "look_at",
    "intrinsics",
    "orbit_position",
    "orbit_basis",
    "capture_up",
    "capture_front",
    "yaw_matrix",
    "orbit_cameras",
    "orbit_camera",
    "orbit_viewmat",
    "ORBIT_KEYS",
    "viewmat_from_opengl_c2w",
    "opengl_c2w_from_viewmat",
    "K_from_normalized",
    "K_from_focal",
    "rodrigues",
    "viewmat_from_rodrigues",
    "camera_center",
    "PIXEL_CENTER",
    "K_from_integer_centers",
    "K_to_integer_centers",
]

ORBIT_KEYS = ("center", "distance", "azimuth_deg", "elevation_deg", "fov_deg", "width", "height", "up", "front")
PIXEL_CENTER = 0.5  # the centre of pixel (i, j) is at (i + 0.5, j + 0.5) under meshsplat's K

_GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])  # flips camera y and z; its own inverse


@dataclass
class Camera:
    """One view: ``viewmat [4,4]`` world->camera (OpenCV), pinhole ``K [3,3]``, image ``width`` x ``height``.

    What datasets hand out (``dataset.camera(id)``, ``dataset.frame_camera(i)``, ``frame.camera``),
    ``orbit_cameras`` makes and ``Avatar.render`` takes. Shapes, float dtypes and positive integer sizes
    are checked on construction; the renderer moves the tensors to the avatar's device and dtype.
    """

    viewmat: torch.Tensor
    K: torch.Tensor
    width: int
    height: int

    def __post_init__(self) -> None:
        check_tensor("camera viewmat", self.viewmat, "4,4", dtype="float")
        check_tensor("camera K", self.K, "3,3", dtype="float")
        for name in ("width", "height"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
                raise MeshsplatError(f"camera {name}: expected a positive integer, got {value!r}")
            setattr(self, name, int(value))

    def to(self, device: torch.device | str | None = None, dtype: torch.dtype | None = None) -> Camera:
        """The same camera with its tensors on ``device`` / in ``dtype`` (None keeps each)."""
        return Camera(
            self.viewmat.to(device=device, dtype=dtype), self.K.to(device=device, dtype=dtype), self.width, self.height
        )

    @classmethod
    def from_numpy(cls, viewmat: ArrayLike, K: ArrayLike, width: int, height: int) -> Camera:
        return cls(
            torch.as_tensor(np.asarray(viewmat), dtype=torch.float32),
            torch.as_tensor(np.asarray(K), dtype=torch.float32),
            int(width),
            int(height),
        )

    @property
    def center(self) -> torch.Tensor:
        """Camera position in world coordinates ``[3]``."""
        R, t = self.viewmat[:3, :3], self.viewmat[:3, 3]
        return -R.T @ t

    def project(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Pinhole projection of world ``points [N,3]``: ``(pixels [N,2], depth [N])``. Pixel coordinates
        follow ``PIXEL_CENTER`` (pixel ``(i, j)`` spans ``[i, i+1) x [j, j+1)``, so ``floor`` gives its
        index); depth is the camera-space z (points behind the camera have depth <= 0)."""
        cam = points @ self.viewmat[:3, :3].T + self.viewmat[:3, 3]
        z = cam[:, 2]
        pix = cam @ self.K.T
        return torch.stack([pix[:, 0] / z.clamp_min(1e-9), pix[:, 1] / z.clamp_min(1e-9)], -1), z

    def resized(self, width: int, height: int) -> Camera:
        """Same view at another resolution (intrinsics scaled per axis)."""
        K = self.K.clone()
        K[0] *= width / self.width
        K[1] *= height / self.height
        K[2] = torch.tensor([0.0, 0.0, 1.0], dtype=K.dtype, device=K.device)
        return Camera(self.viewmat, K, int(width), int(height))


# ---------------------------------------------------------------- constructing cameras
def look_at(eye: ArrayLike, target: ArrayLike, up: ArrayLike = (0.0, 1.0, 0.0)) -> np.ndarray:
    """World->camera ``[4,4]``: camera at ``eye`` looking at ``target``; image y points along -up."""
    eye, target, up = (np.asarray(x, np.float64) for x in (eye, target, up))
    fwd = target - eye
    fwd /= np.linalg.norm(fwd)
    right = np.cross(fwd, up)
    if np.linalg.norm(right) < 1e-8:
        right = np.cross(fwd, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(fwd, right)
    R = np.stack([right, down, fwd])
    m = np.eye(4)
    m[:3, :3] = R
    m[:3, 3] = -R @ eye
    return m


def intrinsics(width: int, height: int, fov_deg: float) -> np.ndarray:
    """Square pixels, vertical field of view ``fov_deg``, principal point at the image centre."""
    f = 0.5 * height / math.tan(math.radians(fov_deg) / 2)
    return np.array([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1]], np.float64)


def orbit_basis(up: ArrayLike = (0.0, 1.0, 0.0), front: ArrayLike = (0.0, 0.0, 1.0)) -> np.ndarray:
    """Rows ``[side, up, front] [3,3]``, orthonormal and right-handed: ``up`` normalised, ``front`` made
    perpendicular to it (another axis when it is parallel), ``side = up x front``. The defaults give the
    identity's rows in the order x, y, z (glTF: +y up, +z the front)."""
    u = np.asarray(up, np.float64).reshape(3)
    if not np.isfinite(u).all() or np.linalg.norm(u) < 1e-12:
        raise MeshsplatError(f"up: expected a finite non-zero 3-vector, got {np.asarray(up).tolist()}")
    u = u / np.linalg.norm(u)
    f = np.asarray(front, np.float64).reshape(3)
    f = f - np.dot(f, u) * u
    if not np.isfinite(f).all() or np.linalg.norm(f) < 1e-6:
        for axis in np.eye(3)[[2, 0, 1]]:
            f = axis - np.dot(axis, u) * u
            if np.linalg.norm(f) > 1e-3:
                break
    f = f / np.linalg.norm(f)
    return np.stack([np.cross(u, f), u, f])


def orbit_position(
    center: ArrayLike,
    distance: float,
    azimuth: float,
    elevation: float,
    up: ArrayLike = (0.0, 1.0, 0.0),
    front: ArrayLike = (0.0, 0.0, 1.0),
) -> np.ndarray:
    """Point at ``distance`` from ``center``; azimuth 0 is ``front`` (default +z, the glTF front), elevation
    towards ``up`` (default +y), angles in radians (:func:`orbit_basis`)."""
    c = np.asarray(center, np.float64)
    side, u, f = orbit_basis(up, front)
    ce = math.cos(elevation)
    return c + distance * (ce * math.sin(azimuth) * side + math.sin(elevation) * u + ce * math.cos(azimuth) * f)


def capture_up(viewmats: Sequence[ArrayLike], snap_deg: float = 30.0) -> np.ndarray:
    """The world's up direction ``[3]`` as a capture's cameras see it: the mean of their up vectors (each
    OpenCV camera's -y axis in world coordinates), snapped to the nearest world axis (+-x, +-y, +-z) when
    within ``snap_deg`` of it (cameras looking down at a subject tilt the mean). +y without cameras."""
    ups = [-np.asarray(vm, np.float64)[1, :3] for vm in viewmats]
    if not ups:
        return np.array([0.0, 1.0, 0.0])
    m = np.mean(ups, axis=0)
    if not np.isfinite(m).all() or np.linalg.norm(m) < 1e-6:  # cameras disagree completely
        return np.array([0.0, 1.0, 0.0])
    m = m / np.linalg.norm(m)
    k = int(np.argmax(np.abs(m)))
    if abs(m[k]) >= math.cos(math.radians(snap_deg)):
        m = np.zeros(3)
        m[k] = 1.0 if np.mean(ups, axis=0)[k] > 0 else -1.0
    return m


def capture_front(viewmat: ArrayLike, center: ArrayLike, up: ArrayLike) -> np.ndarray:
    """Front ``[3]`` for orbit cameras (azimuth 0): the direction from ``center`` (the subject) to the camera
    ``viewmat``, level with ``up`` (a capture's subject faces its camera), whatever the world's axes (a
    +y-up world may have its camera on either side; synthesized captures put it on +z, their front)."""
    u = np.asarray(up, np.float64).reshape(3)
    d = camera_center(viewmat) - np.asarray(center, np.float64).reshape(3)
    return orbit_basis(u, d)[2]


def yaw_matrix(angle: float) -> np.ndarray:
    """Rotation about +y by ``angle`` radians ``[3,3]``."""
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def orbit_cameras(
    vertices: Sequence[torch.Tensor] | torch.Tensor,
    width: int,
    height: int,
    num_frames: int | None = None,
    orbit_deg: float = 0.0,
    azimuth_deg: float = 0.0,
    elevation_deg: float = 10.0,
    distance: float | None = None,
    fov_deg: float = 30.0,
    margin: float = 1.05,
    up: ArrayLike = (0.0, 1.0, 0.0),
    front: ArrayLike = (0.0, 0.0, 1.0),
    center: ArrayLike | None = None,
) -> list[Camera]:
    """Cameras looking at the bounding box of all ``vertices`` (frames of ``[V,3]``), ``up`` up (default +y).

    The camera turns ``orbit_deg`` in total about the ``up`` axis through ``center`` (default the box
    centre; the player page's orbit centre) over ``num_frames`` (default ``len(vertices)``), starting at
    ``azimuth_deg`` (0 = looking from ``front``, default +z, the glTF front). ``distance`` defaults to
    fitting the box's bounding sphere (times ``margin``) in the view. A capture's own up and front:
    ``dataset.up``, ``dataset.front``. Each camera is :func:`orbit_camera`'s, as the page's is.
    """
    if width < 1 or height < 1:
        raise MeshsplatError(f"size: expected a positive width and height, got {width}x{height}")
    if not 1.0 <= fov_deg < 179.0:
        raise MeshsplatError(f"fov_deg: expected in [1, 179), got {fov_deg}")
    lo = hi = None
    count = 0
    for v in vertices:
        v = v.detach().float().reshape(-1, 3)
        lo = v.min(0).values if lo is None else torch.minimum(lo, v.min(0).values)
        hi = v.max(0).values if hi is None else torch.maximum(hi, v.max(0).values)
        count += 1
    if count == 0 or lo is None or hi is None:
        raise MeshsplatError("vertices: no frames to frame the camera on")
    n = count if num_frames is None else int(num_frames)
    box_center = ((lo + hi) / 2).double().numpy()
    c = box_center if center is None else _point("center", center)
    radius = max(float((hi - lo).norm()) / 2, 1e-6) + float(np.linalg.norm(c - box_center))
    K = intrinsics(width, height, fov_deg)
    half = min(math.atan(0.5 * height / K[1, 1]), math.atan(0.5 * width / K[0, 0]))
    dist = margin * radius / math.sin(half) if distance is None else float(distance)
    if not dist > 0:
        raise MeshsplatError(f"distance: expected > 0, got {distance}")
    return [
        orbit_camera(
            c,
            dist,
            azimuth_deg + (orbit_deg * i / n if n > 1 else 0.0),
            elevation_deg,
            fov_deg,
            width,
            height,
            up,
            front,
        )
        for i in range(n)
    ]


def orbit_camera(
    center: ArrayLike,
    distance: float,
    azimuth_deg: float = 0.0,
    elevation_deg: float = 10.0,
    fov_deg: float = 30.0,
    width: int = 800,
    height: int = 800,
    up: ArrayLike = (0.0, 1.0, 0.0),
    front: ArrayLike = (0.0, 0.0, 1.0),
) -> Camera:
    """The camera of an orbit description, the player page's camera language (its ``avatar.json``
    ``camera``: ``center``, ``distance``, ``azimuth_deg``, ``elevation_deg``, ``fov_deg``, ``width``,
    ``height``, ``up``, ``front``): at ``distance`` from ``center`` (:func:`orbit_position`), looking at
    it with ``up`` up, vertical field of view ``fov_deg`` (:func:`intrinsics`)."""
    if width < 1 or height < 1:
        raise MeshsplatError(f"size: expected a positive width and height, got {width}x{height}")
    if not 1.0 <= fov_deg < 179.0:
        raise MeshsplatError(f"fov_deg: expected in [1, 179), got {fov_deg}")
    if not (math.isfinite(distance) and distance > 0):
        raise MeshsplatError(f"distance: expected > 0, got {distance}")
    vm = orbit_viewmat(center, distance, azimuth_deg, elevation_deg, up, front)
    return Camera.from_numpy(vm, intrinsics(width, height, fov_deg), width, height)


def orbit_viewmat(
    center: ArrayLike,
    distance: float,
    azimuth_deg: float,
    elevation_deg: float,
    up: ArrayLike = (0.0, 1.0, 0.0),
    front: ArrayLike = (0.0, 0.0, 1.0),
) -> np.ndarray:
    """World->camera ``[4,4]`` (float64) of an orbit: the page's ``orbitViewmat`` (viewer.js), angles in degrees."""
    c = _point("center", center)
    _, u, f = orbit_basis(up, front)
    eye = orbit_position(c, distance, math.radians(azimuth_deg), math.radians(elevation_deg), u, f)
    return look_at(eye, c, u)


def _point(name: str, p: ArrayLike) -> np.ndarray:
    a = np.asarray(p.detach().cpu() if isinstance(p, torch.Tensor) else p, np.float64)
    if a.shape != (3,) or not np.isfinite(a).all():
        raise MeshsplatError(f"{name}: expected a finite point X,Y,Z, got {a.tolist()}")
    return a


# ---------------------------------------------------------------- converters from other conventions
def _mat(name: str, m: ArrayLike, shape: tuple[int, ...]) -> np.ndarray:
    a = np.asarray(m, np.float64)
    if a.shape != shape or not np.isfinite(a).all():
        raise MeshsplatError(f"{name}: expected a finite {'x'.join(map(str, shape))} matrix, got shape {list(a.shape)}")
    return a


def viewmat_from_opengl_c2w(c2w: ArrayLike) -> np.ndarray:
    """World->camera OpenCV ``[4,4]`` from an OpenGL camera->world ``[4,4]`` (or ``[3,4]``).

    OpenGL cameras look down -z with y up; flipping the camera's y and z axes gives OpenCV's.
    """
    a = np.asarray(c2w, np.float64)
    if a.shape == (3, 4):
        a = np.vstack([a, [0.0, 0.0, 0.0, 1.0]])
    a = _mat("transform_matrix", a, (4, 4))
    return np.linalg.inv(a @ _GL_TO_CV)


def opengl_c2w_from_viewmat(viewmat: ArrayLike) -> np.ndarray:
    """Inverse of :func:`viewmat_from_opengl_c2w`."""
    return np.linalg.inv(_mat("viewmat", viewmat, (4, 4))) @ _GL_TO_CV


def K_from_focal(fl_x: float, fl_y: float, cx: float, cy: float) -> np.ndarray:
    """Pinhole ``K [3,3]`` from focal lengths and principal point in pixels."""
    return np.array([[float(fl_x), 0.0, float(cx)], [0.0, float(fl_y), float(cy)], [0.0, 0.0, 1.0]])


def K_from_normalized(intr: ArrayLike, width: int, height: int) -> np.ndarray:
    """``K`` from ``[fx/W, fy/H, cx/W, cy/H]`` (IMavatar/DECA; signs are dropped: DECA stores fx < 0)."""
    a = np.abs(np.asarray(intr, np.float64).reshape(-1))
    if a.shape != (4,) or not np.isfinite(a).all():
        raise MeshsplatError(
            f"intrinsics: expected 4 finite numbers [fx/W, fy/H, cx/W, cy/H], got {list(np.shape(intr))}"
        )
    return K_from_focal(a[0] * width, a[1] * height, a[2] * width, a[3] * height)


def K_from_integer_centers(K: ArrayLike) -> np.ndarray:
    """meshsplat's ``K`` from one whose pixel centres sit at integer coordinates (OpenCV, InstantAvatar,
    IMavatar): the principal point moves by ``+PIXEL_CENTER`` on both axes, focal lengths unchanged."""
    out = _mat("K", K, (3, 3)).copy()
    out[0, 2] += PIXEL_CENTER
    out[1, 2] += PIXEL_CENTER
    return out


def K_to_integer_centers(K: ArrayLike) -> np.ndarray:
    """Inverse of :func:`K_from_integer_centers` (for writers of integer-centre layouts)."""
    out = _mat("K", K, (3, 3)).copy()
    out[0, 2] -= PIXEL_CENTER
    out[1, 2] -= PIXEL_CENTER
    return out


def rodrigues(rvec: ArrayLike) -> np.ndarray:
    """Rotation matrix ``[3,3]`` of an axis-angle vector ``[3]`` (radians)."""
    r = _mat("rvec", np.asarray(rvec, np.float64).reshape(-1), (3,))
    theta = float(np.linalg.norm(r))
    if theta < 1e-12:
        return np.eye(3)
    k = r / theta
    Kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(theta) * Kx + (1 - math.cos(theta)) * (Kx @ Kx)


def viewmat_from_rodrigues(rvec: ArrayLike, t: ArrayLike) -> np.ndarray:
    """World->camera ``[4,4]`` from a Rodrigues rotation vector and a translation (OpenCV ``rvec, tvec``)."""
    m = np.eye(4)
    m[:3, :3] = rodrigues(rvec)
    m[:3, 3] = _mat("t", np.asarray(t, np.float64).reshape(-1), (3,))
    return m


def camera_center(viewmat: ArrayLike) -> np.ndarray:
    """Camera position ``[3]`` in world coordinates of a world->camera ``[4,4]``."""
    vm = _mat("viewmat", viewmat, (4, 4))
    return -vm[:3, :3].T @ vm[:3, 3]
