"""meshsplat.render.rasterize: contract, validation, backend choice and geometric properties."""

from __future__ import annotations

import importlib.util
import sys

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from meshsplat.errors import MeshsplatError
from meshsplat.render import RenderOutput, rasterize
from meshsplat.render import api as render_api
from meshsplat.render.backends import NO_NUMBA_ENV, numba_available, torch_ref


def simple_scene(n=5, dtype=torch.float32, C=2):
    g = torch.Generator().manual_seed(0)
    means = torch.randn(n, 3, generator=g, dtype=dtype) * 0.3
    means[:, 2] += 3.0
    quats = torch.randn(n, 4, generator=g, dtype=dtype)
    scales = torch.rand(n, 3, generator=g, dtype=dtype) * 0.2 + 0.05
    opac = torch.rand(n, generator=g, dtype=dtype) * 0.8 + 0.1
    colors = torch.rand(n, 3, generator=g, dtype=dtype)
    viewmats = torch.eye(4, dtype=dtype).expand(C, 4, 4).clone()
    Ks = torch.tensor([[30.0, 0, 16], [0, 30, 12], [0, 0, 1]], dtype=dtype).expand(C, 3, 3).clone()
    return dict(
        means=means,
        quats=quats,
        scales=scales,
        opacities=opac,
        colors=colors,
        viewmats=viewmats,
        Ks=Ks,
        width=32,
        height=24,
    )


def test_output_contract_and_means2d_grad():
    s = simple_scene()
    s["means"].requires_grad_(True)
    out = rasterize(**s, backend="torch")
    assert isinstance(out, RenderOutput)
    colors, alphas, meta = out  # unpacks like gsplat
    assert colors.shape == (2, 24, 32, 3) and alphas.shape == (2, 24, 32, 1)
    assert meta["means2d"].shape == (2, 5, 2)
    assert meta["radii"].shape == (2, 5, 2) and meta["radii"].dtype == torch.int32
    assert meta["depths"].shape == (2, 5) and meta["visible"].dtype == torch.bool
    assert (meta["width"], meta["height"], meta["n_cameras"]) == (32, 24, 2)
    assert bool(meta["visible"].all())
    torch.testing.assert_close(meta["depths"][0], s["means"][:, 2].detach())
    assert float(alphas.detach().min()) >= 0 and float(alphas.detach().max()) <= 1
    colors.sum().backward()
    g2 = meta["means2d"].grad
    assert g2 is not None and g2.shape == (2, 5, 2) and float(g2.abs().sum()) > 0
    assert s["means"].grad is not None


def test_projection_matches_pinhole_and_pixel_centres():
    s = simple_scene(n=1, C=1)
    s["means"] = torch.tensor([[0.2, -0.1, 2.0]])
    out = rasterize(**s, backend="torch")
    fx, cx, cy = 30.0, 16.0, 12.0
    torch.testing.assert_close(out.meta["means2d"][0, 0], torch.tensor([fx * 0.1 + cx, fx * -0.05 + cy]))
    # an isotropic splat centred on pixel (5, 7)'s centre peaks exactly there
    s["means"] = torch.tensor([[(5.5 - cx) / fx * 2.0, (7.5 - cy) / fx * 2.0, 2.0]])
    s["scales"] = torch.full((1, 3), 0.03)
    s["quats"] = torch.tensor([[1.0, 0, 0, 0]])
    img = rasterize(**s, backend="torch").alphas[0, ..., 0]
    assert divmod(int(img.argmax()), 32) == (7, 5)


def test_behind_camera_and_far_offscreen_are_culled():
    s = simple_scene(n=3, C=1)
    s["means"] = torch.tensor([[0.0, 0.0, -2.0], [0.0, 0.0, 0.005], [50.0, 0.0, 3.0]])
    out = rasterize(**s, backend="torch")
    assert not bool(out.meta["visible"].any())
    assert int(out.meta["radii"].abs().sum()) == 0
    assert float(out.alphas.abs().max()) == 0.0
    out = rasterize(**s, far_plane=1.0, backend="torch")
    assert not bool(out.meta["visible"].any())


def test_depth_channel_is_expected_depth():
    s = simple_scene(n=1, C=1)
    s["means"] = torch.tensor([[0.0, 0.0, 2.5]])
    out = rasterize(**s, render_mode="RGB+ED", backgrounds=torch.ones(1, 3), backend="torch")
    assert out.colors.shape[-1] == 4
    mask = out.alphas[..., 0] > 0
    torch.testing.assert_close(out.colors[..., 3][mask], torch.full_like(out.colors[..., 3][mask], 2.5))


@pytest.mark.parametrize(
    "field,value,needle",
    [
        ("means", torch.zeros(5, 2), "means: expected shape [N,3]"),
        ("quats", torch.zeros(4, 4), "quats: expected shape [N,4]"),
        ("opacities", torch.zeros(5, 1), "opacities"),
        ("colors", torch.zeros(6, 3), "colors"),
        ("viewmats", torch.zeros(2, 3, 4), "viewmats: expected shape [C,4,4]"),
        ("Ks", torch.zeros(3, 3, 3), "Ks: expected shape [C,3,3]"),
        ("means", torch.zeros(5, 3, dtype=torch.int64), "means: expected dtype"),
        ("scales", torch.full((5, 3), float("nan")), "scales: contains"),
        ("width", 0, "width"),
        ("height", 2.5, "height"),
    ],
)
def test_validation_errors_name_the_argument(field, value, needle):
    s = simple_scene()
    s[field] = value
    with pytest.raises(MeshsplatError) as err:
        rasterize(**s)
    assert needle in str(err.value)


def test_other_validation_errors():
    s = simple_scene()
    with pytest.raises(MeshsplatError, match="backgrounds"):
        rasterize(**s, backgrounds=torch.zeros(3, 3))
    with pytest.raises(MeshsplatError, match="render_mode"):
        rasterize(**s, render_mode="D")
    with pytest.raises(MeshsplatError, match="backend"):
        rasterize(**s, backend="vulkan")
    with pytest.raises(MeshsplatError, match="dtype"):
        rasterize(**{**s, "colors": s["colors"].double()})
    with pytest.raises(MeshsplatError, match="near"):
        rasterize(**s, near_plane=2.0, far_plane=1.0)
    with pytest.raises(MeshsplatError, match="unknown backend option"):
        rasterize(**s, backend="torch", tile_size=16)


def test_gsplat_backend_refuses_cpu_tensors():
    with pytest.raises(MeshsplatError, match="CUDA"):
        rasterize(**simple_scene(), backend="gsplat")


def test_auto_never_touches_gsplat_for_cpu(monkeypatch):
    def boom(*args, **kwargs):
        raise AssertionError("gsplat backend called for CPU tensors")

    monkeypatch.setattr(render_api, "gsplat_available", lambda: True)  # even if it were installed
    monkeypatch.setattr(render_api, "rasterize_gsplat", boom)
    out = rasterize(**simple_scene(), backend="auto")
    cpu_backend = "numba" if numba_available() else "torch"
    assert out.meta["backend"] == cpu_backend
    assert render_api._pick_backend("auto", torch.device("cpu")) == cpu_backend
    assert "gsplat" not in sys.modules or torch.cuda.is_available()


def test_auto_falls_back_to_torch_without_numba(monkeypatch):
    """MESHSPLAT_NO_NUMBA=1 is what numba_available() checks first: auto then renders with torch on CPU,
    and asking for numba explicitly is a clear error (the same path as numba not being installed)."""
    monkeypatch.setenv(NO_NUMBA_ENV, "1")
    assert not numba_available()
    s = simple_scene()
    s["means"].requires_grad_(True)
    out = rasterize(**s, backend="auto")
    assert out.meta["backend"] == "torch"
    out.colors.sum().backward()
    assert s["means"].grad is not None and float(s["means"].grad.abs().sum()) > 0
    assert render_api._pick_backend("auto", torch.device("cpu")) == "torch"
    with pytest.raises(MeshsplatError, match="needs numba"):
        rasterize(**simple_scene(), backend="numba")
    monkeypatch.setenv(NO_NUMBA_ENV, "0")
    assert numba_available() == (importlib.util.find_spec("numba") is not None)


def test_auto_with_torch_options_uses_torch():
    out = rasterize(**simple_scene(), backend="auto", pair_budget=100)
    assert out.meta["backend"] == "torch"


def test_numba_backend_refuses_non_cpu_and_options():
    with pytest.raises(MeshsplatError, match="CPU tensors"):
        render_api._pick_backend("numba", torch.device("cuda"))
    with pytest.raises(MeshsplatError, match="float32 or float64"):
        render_api._pick_backend("numba", torch.device("cpu"), torch.float16)
    assert render_api._pick_backend("auto", torch.device("cpu"), torch.float16) == "torch"
    if numba_available():
        with pytest.raises(MeshsplatError, match="no backend options"):
            rasterize(**simple_scene(), backend="numba", pair_budget=100)


def test_per_camera_colors():
    s = simple_scene(C=2)
    per_cam = torch.stack([s["colors"], 1 - s["colors"]])
    out = rasterize(**{**s, "colors": per_cam}, backend="torch")
    a = rasterize(**s, backend="torch").colors[0]
    b = rasterize(**{**s, "colors": 1 - s["colors"]}, backend="torch").colors[1]
    torch.testing.assert_close(out.colors[0], a)
    torch.testing.assert_close(out.colors[1], b)


def test_memory_chunking_bounds_pairs_per_band(monkeypatch):
    seen = []
    real = torch_ref._band_pairs

    def spy(plan, b):
        pix, entry = real(plan, b)
        seen.append(pix.shape[0])
        return pix, entry

    monkeypatch.setattr(torch_ref, "_band_pairs", spy)
    s = simple_scene(n=30, C=1)
    out = rasterize(**s, backend="torch", pair_budget=200)
    assert len(seen) > 3
    # a band exceeds the budget only when a single image row holds more pairs than it
    assert max(seen) <= max(200, 32 * 30)
    assert sum(seen) == out.meta["n_pairs"]


@settings(max_examples=15)
@given(c=st.floats(0.0, 1.0), seed=st.integers(0, 10_000))
def test_constant_colour_everywhere_when_background_matches(c, seed):
    """sum_i w_i + T_final = 1 per pixel, so one colour for all splats and background is exact."""
    g = torch.Generator().manual_seed(seed)
    s = simple_scene(n=20, dtype=torch.float64, C=1)
    s["means"] = torch.randn(20, 3, generator=g, dtype=torch.float64) * 0.4 + torch.tensor(
        [0, 0, 3.0], dtype=torch.float64
    )
    s["colors"] = torch.full((20, 3), c, dtype=torch.float64)
    out = rasterize(**s, backgrounds=torch.full((1, 3), c, dtype=torch.float64), backend="torch")
    torch.testing.assert_close(out.colors, torch.full_like(out.colors, c), atol=1e-12, rtol=0)


@settings(max_examples=15)
@given(shift_x=st.integers(-6, 6), shift_y=st.integers(-6, 6), seed=st.integers(0, 10_000))
def test_integer_principal_point_shift_translates_image(shift_x, shift_y, seed):
    g = torch.Generator().manual_seed(seed)
    s = simple_scene(n=12, dtype=torch.float64, C=1)
    s["means"] = torch.randn(12, 3, generator=g, dtype=torch.float64) * 0.25 + torch.tensor(
        [0, 0, 3.0], dtype=torch.float64
    )
    s["width"], s["height"] = 48, 40
    s["Ks"] = torch.tensor([[[40.0, 0, 24], [0, 40, 20], [0, 0, 1]]], dtype=torch.float64)
    base = rasterize(**s, backend="torch").colors[0]
    K2 = s["Ks"].clone()
    K2[0, 0, 2] += shift_x
    K2[0, 1, 2] += shift_y
    moved = rasterize(**{**s, "Ks": K2}, backend="torch").colors[0]
    H, W = 40, 48
    ys, xs = slice(max(shift_y, 0), H + min(shift_y, 0)), slice(max(shift_x, 0), W + min(shift_x, 0))
    ys0, xs0 = slice(max(-shift_y, 0), H + min(-shift_y, 0)), slice(max(-shift_x, 0), W + min(-shift_x, 0))
    # splats near the border differ only through the (shift-dependent) off-screen Jacobian clamp
    torch.testing.assert_close(moved[ys, xs][8:-8, 8:-8], base[ys0, xs0][8:-8, 8:-8], atol=1e-9, rtol=0)


def test_backends_take_keywords_only():
    """The front door forwards by name: a reordered backend signature cannot misroute arguments."""
    import inspect

    from meshsplat.render.backends.gsplat_cuda import rasterize_gsplat
    from meshsplat.render.backends.torch_ref import rasterize_torch

    for fn in (rasterize_torch, rasterize_gsplat):
        params = inspect.signature(fn).parameters.values()
        assert all(p.kind is inspect.Parameter.KEYWORD_ONLY for p in params), fn.__name__
