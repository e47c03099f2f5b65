"""Plausible ranges of what captures and drivers hand over: cameras, body-model parameters, skinning weights.

The one home of these limits. Each check returns problem lines (empty when plausible) that say what was
found and what was expected; readers add them to their ``Problems``, drivers raise them as one
``MeshsplatError`` line. Frames are listed grouped (``"frames 3-17"``, :func:`group_ids`).

- cameras: a pinhole focal length between ``MIN_FOCAL_FACTOR`` and ``MAX_FOCAL_FACTOR`` times the
  image's longer side (a field of view between about 0.6 and 170 degrees);
- axis-angle poses: every joint's rotation angle at most ``MAX_AXIS_ANGLE`` radians (a pose given in
  degrees reads as tens of radians);
- shape and expression coefficients (in standard deviations of the model's PCA): at most
  ``MAX_COEFFICIENT`` in magnitude;
- every value finite;
- skinning weights: every vertex with a positive weight sum (an all-zero row collapses to the origin);
- numbered sequences (timesteps, frame files): no gap wider than their usual step (it plays as a jump).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

import numpy as np

__all__ = [
    "MIN_FOCAL_FACTOR",
    "MAX_FOCAL_FACTOR",
    "MAX_AXIS_ANGLE",
    "MAX_COEFFICIENT",
    "AXIS_ANGLE_KEYS",
    "COEFFICIENT_KEYS",
    "group_ids",
    "focal_problem",
    "parameter_problems",
    "skinning_problem",
    "sequence_gaps",
]

MIN_FOCAL_FACTOR = 0.05  # focal length / longer image side: wider than ~170 degrees is no pinhole
MAX_FOCAL_FACTOR = 100.0  # narrower than ~0.6 degrees sees a speck, not a subject
MAX_AXIS_ANGLE = 2.0 * math.pi + 0.5  # radians per joint; a fitter may wrap past pi, not far past 2 pi
MAX_COEFFICIENT = 50.0  # shape/expression PCA coefficients are in standard deviations (typically within 5)

# parameter names (of every layout the readers and motion files use) holding axis-angle rotations
AXIS_ANGLE_KEYS = frozenset(
    {
        "global_orient",
        "body_pose",
        "jaw_pose",
        "leye_pose",
        "reye_pose",
        "neck_pose",
        "eyes_pose",
        "left_hand_pose",
        "right_hand_pose",
        "poses",
        "pose",
        "thetas",
        "root_orient",
        "rotation",
    }
)
COEFFICIENT_KEYS = frozenset({"betas", "shape", "expression", "expr"})


def group_ids(ids: Iterable[Any], limit: int = 8) -> str:
    """``[3, 4, 5, 9]`` -> ``"3-5, 9"`` (an en dash in the text) (at most ``limit`` groups, then how many more)."""
    ids = sorted(set(int(i) for i in ids))
    groups: list[list[int]] = []
    for i in ids:
        if groups and i == groups[-1][1] + 1:
            groups[-1][1] = i
        else:
            groups.append([i, i])
    shown = [f"{a}" if a == b else f"{a}\u2013{b}" for a, b in groups[:limit]]
    rest = sum(b - a + 1 for a, b in groups[limit:])
    return ", ".join(shown) + (f" and {rest} more" if rest else "")


def focal_problem(K: Any, width: int, height: int) -> str | None:
    """Why the pinhole ``K [3,3]`` cannot frame a subject in a ``width x height`` image, or None."""
    K = np.asarray(K, np.float64)
    side = max(int(width), int(height), 1)
    f = max(abs(float(K[0, 0])), abs(float(K[1, 1])))
    lo, hi = MIN_FOCAL_FACTOR * side, MAX_FOCAL_FACTOR * side
    if lo <= f <= hi:
        return None
    fov = math.degrees(2 * math.atan(side / (2 * f))) if f > 0 else 180.0
    return (
        f"focal length {f:.4g} px gives a {fov:.3g}-degree field of view on a {width}x{height} image; "
        f"expected {lo:.3g} to {hi:.4g} px (pixels, not millimetres or a normalised value?)"
    )


def _frames(rows: np.ndarray) -> str:
    return f"frame {group_ids(rows)}" if len(rows) == 1 else f"frames {group_ids(rows)}"


def _rows_where(bad: np.ndarray) -> np.ndarray:
    """Row indices (first axis) where ``bad`` has any True; ``[0]`` for a scalar or a 1-D shared value."""
    if bad.ndim <= 1:
        return np.zeros(1, np.int64) if bad.any() else np.zeros(0, np.int64)
    return np.nonzero(bad.reshape(bad.shape[0], -1).any(1))[0]


def parameter_problems(params: Mapping[str, Any]) -> list[str]:
    """Problem lines (``"KEY: ..."``) of a parameter dict (arrays ``[T, k]`` or ``[k]``): non-finite values,
    axis-angle rotations beyond ``MAX_AXIS_ANGLE`` (degrees given for radians?), shape/expression
    coefficients beyond ``MAX_COEFFICIENT``. Keys it does not know are checked for finiteness only."""
    lines = []
    for key, value in params.items():
        if hasattr(value, "detach"):
            value = value.detach().cpu().numpy()
        try:
            a = np.asarray(value, np.float64)
        except (TypeError, ValueError):
            continue  # the caller's shape/type check names it
        if a.size == 0:
            continue
        nonfinite = ~np.isfinite(a)
        if nonfinite.any():
            rows = _rows_where(nonfinite)
            where = f" ({_frames(rows)})" if a.ndim >= 2 else ""
            lines.append(f"{key}: {int(nonfinite.sum())} NaN/inf values{where}; expected finite numbers")
            continue
        if key in AXIS_ANGLE_KEYS and a.shape[-1] % 3 == 0:
            angles = np.linalg.norm(a.reshape(*a.shape[:-1], -1, 3), axis=-1)
            bad = angles > MAX_AXIS_ANGLE
            if bad.any():
                rows = _rows_where(bad)
                where = f" ({_frames(rows)})" if a.ndim >= 2 else ""
                lines.append(
                    f"{key}: joint rotations up to {angles.max():.4g} radians{where}; expected axis-angle "
                    f"in radians, at most {MAX_AXIS_ANGLE:.2f} (degrees given for radians?)"
                )
        elif key in COEFFICIENT_KEYS:
            big = np.abs(a) > MAX_COEFFICIENT
            if big.any():
                rows = _rows_where(big)
                where = f" ({_frames(rows)})" if a.ndim >= 2 else ""
                lines.append(
                    f"{key}: coefficients up to {np.abs(a).max():.4g}{where}; expected at most "
                    f"{MAX_COEFFICIENT:g} in magnitude (standard deviations of the model's PCA)"
                )
    return lines


def skinning_problem(weights: Any, what: str = "skinning weights") -> str | None:
    """Why skinning ``weights [V,J]`` cannot pose a mesh (NaN/inf, negative, or vertices whose weights are
    all zero and would collapse to the origin), or None."""
    w = np.asarray(weights, np.float64)
    if w.ndim != 2 or w.size == 0:
        return None  # the caller's shape check names it
    if not np.isfinite(w).all():
        return f"{what}: {int((~np.isfinite(w)).sum())} NaN/inf values; expected finite weights summing to 1"
    if (w < -1e-6).any():
        return f"{what}: {int((w < -1e-6).sum())} negative weights; expected weights in [0, 1] summing to 1"
    zero = np.nonzero(w.sum(1) <= 1e-8)[0]
    if len(zero):
        which = "every vertex has" if len(zero) == len(w) else f"{len(zero)} of {len(w)} vertices have"
        return (
            f"{what}: {which} all-zero weights (those vertices collapse to the origin; vertices "
            f"{group_ids(zero, 4)}); expected weights summing to 1 per vertex"
        )
    return None


def sequence_gaps(numbers: Sequence[int], what: str = "timesteps") -> str | None:
    """The gaps of a numbered sequence (``[0, 1, 2, 5, 6]`` -> 3 and 4 missing), in one line, or None.

    The usual step (the most common difference) is the sequence's stride, so a capture subsampled every
    second frame has no gap; a larger difference does: its frames would play as one jump."""
    nums = sorted(set(int(n) for n in numbers))
    if len(nums) < 3:
        return None
    diffs = np.diff(nums)
    values, counts = np.unique(diffs, return_counts=True)
    stride = int(values[np.argmax(counts)])
    jumps = [(a, b) for a, b in itertools.pairwise(nums) if b - a > stride]
    if not jumps:
        return None
    shown = ", ".join(f"{a} to {b}" for a, b in jumps[:4]) + (f" and {len(jumps) - 4} more" if len(jumps) > 4 else "")
    missing = sum((b - a) // stride - 1 for a, b in jumps)
    step = "" if stride == 1 else f" (stride {stride})"
    return f"{what} jump from {shown}{step}: {missing} missing, played as consecutive frames"
