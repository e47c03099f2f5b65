"""Gaussians to export and the helpers that compare what splat readers read back."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import numpy as np
import pytest


def _gaussians(n=300, k=15, seed=0, extent=1.0):
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(n, 4))
    return {
        "means": rng.normal(size=(n, 3)) * extent,
        "quats": q / np.linalg.norm(q, axis=1, keepdims=True),
        "log_scales": rng.uniform(-6, -1, (n, 3)),
        "opacity_logits": rng.uniform(-4, 4, n),
        "sh0": rng.uniform(-1.5, 1.5, (n, 3)),
        "shN": rng.uniform(-0.5, 0.5, (n, k, 3)),
    }


def _align(b, ref):
    """Index of the reference Gaussian at each read-back position (files may reorder)."""
    d = ((b["means"][:, None] - ref["means"][None]) ** 2).sum(-1)
    idx = d.argmin(1)
    assert len(set(idx.tolist())) == len(idx)
    return idx


def _same_rotation(qa, qb, atol):
    sign = np.where((qa * qb).sum(1, keepdims=True) < 0, -1.0, 1.0)  # q and -q are the same rotation
    np.testing.assert_allclose(qa * sign, qb, atol=atol)


def _sigmoid(x):
    return 1 / (1 + np.exp(-x))


def _node_tool(name: str) -> Path:
    if not NODE_TOOLS or shutil.which("node") is None:
        pytest.skip(
            "set MESHSPLAT_NODE_TOOLS to a folder with node_modules/{@playcanvas/splat-transform,gltf-validator}"
        )
    path = Path(NODE_TOOLS) / "node_modules" / name
    if not path.exists():
        pytest.skip(f"{path} is not installed")
    return path


def _pinned(package: str) -> str:
    """The version of ``package`` that the Makefile installs for these tests (``make node-tools``)."""
    text = (Path(__file__).resolve().parents[1] / "Makefile").read_text()
    return text.split(f"{package}@", 1)[1].split()[0]


# independent Node readers: `make test` installs them into .node-tools (or point MESHSPLAT_NODE_TOOLS elsewhere)
NODE_TOOLS = os.environ.get("MESHSPLAT_NODE_TOOLS") or str(Path(__file__).resolve().parents[1] / ".node-tools")
