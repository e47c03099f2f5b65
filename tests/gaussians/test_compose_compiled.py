"""The compiled compose (``gaussians._compose_numba``) and irradiance (``gaussians._shading_numba``) against the
torch reference: values, gradients (every parameter, the pose's vertices, the shading's coefficients and lights),
float64 gradcheck, the same bits on one and two threads, and bad input refused before a kernel reads it."""

from __future__ import annotations

import pytest
import torch

from meshsplat.errors import MeshsplatError
from meshsplat.gaussians import compose, init_params
from meshsplat.gaussians._compose_numba import compose_geometry_compiled
from meshsplat.gaussians._shading_numba import BLOCK, irradiance_compiled
from meshsplat.gaussians.shading import Shading, sh9_basis
from meshsplat.mesh import MeshPose, TriMesh

pytest.importorskip("numba")


def _sphere(dtype: torch.dtype) -> TriMesh:
    import trimesh

    m = trimesh.creation.icosphere(subdivisions=2)
    return TriMesh(torch.tensor(m.vertices, dtype=dtype), torch.tensor(m.faces, dtype=torch.long))


def _scene(dtype=torch.float32, n=400, sh_degree=0, seed=0):
    """A posed, stretched sphere (vertices that take gradients) and trained-looking parameters: offsets off the
    triangles, tilted rotations, anisotropic scales."""
    gen = torch.Generator().manual_seed(seed)
    mesh = _sphere(dtype)
    verts = mesh.vertices * torch.tensor([1.4, 0.7, 1.0], dtype=dtype)
    verts = (verts + 0.08 * torch.randn(verts.shape, generator=gen, dtype=dtype)).requires_grad_(True)
    params = init_params(mesh, n, sh_degree=sh_degree, generator=gen)
    params = {k: v.to(dtype) if v.is_floating_point() else v for k, v in params.items()}
    params["duv"] = 0.1 * torch.randn(n, 2, generator=gen, dtype=dtype)
    params["d"] = 0.03 * torch.randn(n, generator=gen, dtype=dtype)
    params["rotation"] = torch.randn(n, 4, generator=gen, dtype=dtype)
    params["log_scale"] = params["log_scale"] + 0.5 * torch.randn(n, 3, generator=gen, dtype=dtype)
    params["sh0"] = torch.randn(n, 1, 3, generator=gen, dtype=dtype)
    if "shN" in params:
        params["shN"] = 0.3 * torch.randn(params["shN"].shape, generator=gen, dtype=dtype)
    for v in params.values():
        if v.is_floating_point():
            v.requires_grad_(True)
    return mesh, verts, params


def _lit(dtype, occlusion: str) -> Shading:
    gen = torch.Generator().manual_seed(3)
    coeffs = (0.6 * torch.randn(9, 3, generator=gen, dtype=dtype)).requires_grad_(True)
    if occlusion == "none":
        return Shading(coeffs)
    sh = Shading(coeffs, occlusion=occlusion, directions=6, grid=32)
    assert sh.light is not None
    sh.light = (torch.randn(sh.light.shape, generator=gen, dtype=dtype)).requires_grad_(True)
    return sh


def _near(a: torch.Tensor, b: torch.Tensor, tol: float = 1e-4) -> bool:
    """``b`` within ``tol`` of ``a``, relative to ``a``'s largest entry (at least 1)."""
    a, b = a.detach(), b.detach()
    return float((a - b).abs().max()) <= tol * max(1.0, float(a.abs().max()))


def _compose_and_grads(mesh, verts, params, compiled, **kw):
    pose = MeshPose.from_vertices(mesh, verts)
    g = compose(params, pose, compiled=compiled, **kw)
    outs = [g.means, g.quats, g.scales, g.opacities, g.colors]
    gen = torch.Generator().manual_seed(7)
    loss = sum((o * torch.randn(o.shape, generator=gen, dtype=o.dtype)).sum() for o in outs)
    shading = kw.get("shading")
    inputs = [verts, *(v for v in params.values() if v.requires_grad)]
    if shading is not None:
        inputs += [t for t in shading.parameters() if t.requires_grad]
    return outs, torch.autograd.grad(loss, inputs)


@pytest.mark.parametrize("scale_mode", ["sqrt_area", "area", "none"])
@pytest.mark.parametrize("occlusion", [None, "none", "directions"])
def test_compiled_compose_matches_torch(scale_mode, occlusion):
    mesh, verts, params = _scene()
    kw = {"scale_mode": scale_mode}
    if occlusion is not None:
        kw["shading"] = _lit(torch.float32, occlusion)
    ref_out, ref_grads = _compose_and_grads(mesh, verts, params, False, **kw)
    out, grads = _compose_and_grads(mesh, verts, params, True, **kw)
    for a, b in zip(ref_out, out, strict=True):
        assert _near(a, b, 1e-5)
    for a, b in zip(ref_grads, grads, strict=True):
        assert _near(a, b)


def test_compiled_compose_matches_torch_with_view_dependence_in_the_triangle_frame_and_clamping():
    mesh, verts, params = _scene(sh_degree=2)
    kw = {"campos": torch.tensor([0.3, 0.5, 4.0]), "sh_frame": "triangle", "clamp_to_face": True}
    ref_out, ref_grads = _compose_and_grads(mesh, verts, params, False, **kw)
    out, grads = _compose_and_grads(mesh, verts, params, True, **kw)
    for a, b in zip(ref_out + list(ref_grads), out + list(grads), strict=True):
        assert _near(a, b)


def test_compiled_geometry_gradcheck_float64():
    mesh, verts, params = _scene(torch.float64, n=24)
    pose = MeshPose.from_vertices(mesh, verts)
    uv = (params["uv"] + params["duv"]).detach().requires_grad_(True)
    table = [pose.verts, pose.vertex_normals, pose.vertex_quats, pose.area_ratio]
    table = [t.detach().requires_grad_(True) for t in table]
    for mode in ("sqrt_area", "area", "none"):

        def f(v, n, q, r, uv_, d, rot, ls, mode=mode):
            return compose_geometry_compiled(v, n, q, r, pose.faces, params["face"], uv_, d, rot, ls, mode)[:5]

        args = (*table, uv, *(params[k].detach().requires_grad_(True) for k in ("d", "rotation", "log_scale")))
        assert torch.autograd.gradcheck(f, args, eps=1e-6, atol=1e-6)


def test_compiled_irradiance_gradcheck_float64():
    gen = torch.Generator().manual_seed(0)
    n = torch.nn.functional.normalize(torch.randn(30, 3, generator=gen, dtype=torch.float64), dim=-1)
    coeffs = torch.randn(9, 3, generator=gen, dtype=torch.float64)
    dirs = torch.nn.functional.normalize(torch.randn(4, 3, generator=gen, dtype=torch.float64), dim=-1)
    light = torch.randn(4, 3, generator=gen, dtype=torch.float64)
    vis = torch.rand(30, 4, generator=gen, dtype=torch.float64)
    args = tuple(t.requires_grad_(True) for t in (n, coeffs, light))
    assert torch.autograd.gradcheck(lambda a, b, c: irradiance_compiled(a, b, dirs, c, vis), args, eps=1e-6)
    assert torch.autograd.gradcheck(lambda a, b: irradiance_compiled(a, b), args[:2], eps=1e-6)
    ref = (sh9_basis(n) @ coeffs).clamp_min(0) + (vis * (n @ dirs.T).clamp_min(0)) @ light.clamp_min(0)
    assert torch.allclose(irradiance_compiled(n, coeffs, dirs, light, vis), ref, atol=1e-12)


def test_compiled_compose_gives_the_same_bits_on_one_and_two_threads():
    mesh, verts, params = _scene(n=3 * BLOCK + 17)  # several blocks of the irradiance's gradient sums
    kw = {"shading": _lit(torch.float32, "directions")}
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        one = _compose_and_grads(mesh, verts, params, True, **kw)
        torch.set_num_threads(2)
        two = _compose_and_grads(mesh, verts, params, True, **kw)
    finally:
        torch.set_num_threads(before)
    for a, b in zip(one[0] + list(one[1]), two[0] + list(two[1]), strict=True):
        assert torch.equal(a, b)


def test_compiled_compose_keeps_degenerate_inputs_finite_as_torch_does():
    mesh, verts, params = _scene(n=64)
    with torch.no_grad():
        params["rotation"][:8] = 0.0  # a zero quaternion: normalised by the clamped norm
        params["duv"][8:16] = torch.tensor([5.0, -7.0])  # far outside the triangle (extrapolated)
    ref_out, ref_grads = _compose_and_grads(mesh, verts, params, False)
    out, grads = _compose_and_grads(mesh, verts, params, True)
    for a, b in zip(ref_out + list(ref_grads), out + list(grads), strict=True):
        assert torch.isfinite(b).all()
        assert _near(a, b)


def test_compiled_compose_refuses_a_face_index_outside_the_mesh():
    mesh, verts, params = _scene(n=16)
    params["face"] = params["face"].clone()
    params["face"][3] = mesh.num_faces + 5
    with pytest.raises(MeshsplatError, match="face: indices must lie in"):
        compose(params, MeshPose.from_vertices(mesh, verts), compiled=True)
