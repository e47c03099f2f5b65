"""Thresholds shared by every rasterizer backend (the gsplat 1.5.3 values)."""

from __future__ import annotations

import math

from meshsplat.camera import PIXEL_CENTER  # the camera convention's one home: K maps pixel (i, j) to (i+0.5, j+0.5)

__all__ = [
    "ALPHA_THRESHOLD",
    "ALPHA_MAX",
    "TRANSMITTANCE_MIN",
    "LOG_TRANSMITTANCE_MIN",
    "EPS2D",
    "MAX_EXTEND",
    "FOV_CLAMP_MARGIN",
    "DEPTH_ALPHA_MIN",
    "PIXEL_CENTER",
    "SPAN_MARGIN",
]

ALPHA_THRESHOLD = 1.0 / 255.0  # a splat with alpha below this is skipped for that pixel
ALPHA_MAX = 0.999  # alpha = min(ALPHA_MAX, opacity * exp(-sigma)) (gsplat kernel; 3DGS used 0.99)
TRANSMITTANCE_MIN = 1e-4  # stop before the splat that would take T to <= this
LOG_TRANSMITTANCE_MIN = math.log(TRANSMITTANCE_MIN)
EPS2D = 0.3  # low-pass dilation added to the diagonal of every 2D covariance (pixels^2)
MAX_EXTEND = 3.33  # footprint half-size in sigmas (opacity-aware: min(3.33, sqrt(2 ln(255 o))))
FOV_CLAMP_MARGIN = 0.3  # Jacobian clamps x/z, y/z to the frustum widened by 0.3 * tan(fov/2) per side
DEPTH_ALPHA_MIN = 1e-10  # expected depth = accumulated depth / max(alpha, this)
SPAN_MARGIN = 0.05  # pixels of slack on the closed-form footprint's rows and columns (the alpha test is exact)
