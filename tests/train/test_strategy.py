"""Densification ops and strategy: every per-Gaussian tensor and Adam moment stays aligned."""

from __future__ import annotations

import math

import pytest
import torch

from _meshes import plane
from meshsplat.gaussians import compose, init_params
from meshsplat.mesh import MeshPose
from meshsplat.train.optim import build_optimizers
from meshsplat.train.strategy import (
    DensifyStrategy,
    duplicate,
    remove,
    reset_opacity,
    walk_embeddings,
)
from meshsplat.train.strategy.ops import split_append

LRS = {"duv": 1e-3, "d": 1e-3, "sh0": 1e-3, "shN": 1e-3, "opacity_logit": 1e-3, "log_scale": 1e-3, "rotation": 1e-3}
FLOAT_KEYS = ("rotation", "log_scale", "opacity_logit", "sh0", "shN", "duv", "d", "uv")


def tagged_setup(n: int = 40, sh_degree: int = 1):
    """Params whose every row encodes its id, optimizers whose moments encode it too."""
    mesh = plane()
    p = init_params(mesh, n, sh_degree=sh_degree, generator=torch.Generator().manual_seed(0))
    opts = build_optimizers(p, LRS)
    # one real Adam step so that the state exists
    loss = sum((v.float() ** 2).sum() for k, v in p.items() if k in opts)
    loss.backward()
    for o in opts.values():
        o.step()
        o.zero_grad()
    ids = torch.arange(n, dtype=torch.float32)
    with torch.no_grad():
        for i, k in enumerate(FLOAT_KEYS):
            if k in p:
                v = p[k]
                v.copy_((ids + 1000 * i).reshape((n,) + (1,) * (v.ndim - 1)).expand_as(v))
        p["face"].copy_(torch.arange(n) % mesh.num_faces)
    for k, o in opts.items():
        st = o.state[p[k]]
        st["exp_avg"].copy_((ids + 0.5).reshape((n,) + (1,) * (p[k].ndim - 1)).expand_as(p[k]))
        st["exp_avg_sq"].copy_((ids + 0.25).reshape((n,) + (1,) * (p[k].ndim - 1)).expand_as(p[k]))
    state = {"grad2d": ids.clone(), "count": ids + 1, "radii": ids * 2, "extent": 1.0}
    return mesh, p, opts, state


def row_id(p, r: int) -> int:
    return int(p["opacity_logit"][r].item()) - 2000


def assert_aligned(p, opts, state, n_faces: int, fresh_rows=()):
    n = p["face"].shape[0]
    for k, v in p.items():
        assert v.shape[0] == n, k
    for k, o in opts.items():
        assert o.param_groups[0]["params"][0] is p[k], k
        st = o.state[p[k]]
        assert st["exp_avg"].shape == p[k].shape and st["exp_avg_sq"].shape == p[k].shape
    for name in ("grad2d", "count", "radii"):
        assert state[name].shape[0] == n
    for r in range(n):
        i = row_id(p, r)
        assert int(p["face"][r]) == i % n_faces
        for j, k in enumerate(FLOAT_KEYS):
            if k in p:
                assert torch.all(p[k][r] == i + 1000 * j), (k, r)
        for k, o in opts.items():
            st = o.state[p[k]]
            want_m, want_v = (0.0, 0.0) if r in fresh_rows else (i + 0.5, i + 0.25)
            assert torch.all(st["exp_avg"][r] == want_m) and torch.all(st["exp_avg_sq"][r] == want_v), (k, r)


def test_duplicate_keeps_everything_aligned():
    mesh, p, opts, state = tagged_setup()
    mask = torch.zeros(40, dtype=torch.bool)
    mask[[3, 7, 11]] = True
    duplicate(p, opts, state, mask)
    assert p["face"].shape[0] == 43
    assert [row_id(p, r) for r in (40, 41, 42)] == [3, 7, 11]
    assert_aligned(p, opts, state, mesh.num_faces, fresh_rows=(40, 41, 42))
    assert torch.all(state["grad2d"][40:] == 0)


def test_remove_keeps_everything_aligned():
    mesh, p, opts, state = tagged_setup()
    mask = torch.zeros(40, dtype=torch.bool)
    mask[::3] = True
    remove(p, opts, state, mask)
    assert p["face"].shape[0] == 40 - 14
    assert [row_id(p, r) for r in range(4)] == [1, 2, 4, 5]
    assert_aligned(p, opts, state, mesh.num_faces)
    assert torch.equal(state["radii"], torch.tensor([i * 2.0 for i in range(40) if i % 3]))


def test_split_append_replaces_parents_with_children():
    _mesh, p, opts, state = tagged_setup()
    mask = torch.zeros(40, dtype=torch.bool)
    mask[[5, 9]] = True
    new = {
        "face": torch.tensor([1, 2, 3, 4]),
        "uv": torch.full((4, 2), 0.25),
        "d": torch.full((4,), 0.5),
        "log_scale": torch.full((4, 3), -7.0),
    }
    split_append(p, opts, state, mask, new, 2)
    assert p["face"].shape[0] == 42
    assert [row_id(p, r) for r in range(38, 42)] == [5, 9, 5, 9]  # repeat-major
    assert torch.equal(p["face"][38:], new["face"]) and torch.all(p["uv"][38:] == 0.25)
    assert torch.all(p["d"][38:] == 0.5) and torch.all(p["log_scale"][38:] == -7)
    assert torch.all(p["duv"][38:] == 0)
    assert torch.equal(p["rotation"][38], p["rotation"][40])
    for k, o in opts.items():
        assert o.param_groups[0]["params"][0] is p[k]
        assert torch.all(o.state[p[k]]["exp_avg"][38:] == 0)
        assert torch.all(o.state[p[k]]["exp_avg"][:38] != 0)
    assert [row_id(p, r) for r in range(38)] == [i for i in range(40) if i not in (5, 9)]
    assert state["grad2d"].shape[0] == 42 and torch.all(state["grad2d"][38:] == 0)


def test_reset_opacity_in_place_zeroes_moments():
    _mesh, p, opts, _state = tagged_setup()
    with torch.no_grad():
        p["opacity_logit"].copy_(torch.linspace(-6, 6, 40))
    obj = p["opacity_logit"]
    reset_opacity(p, opts, 0.01)
    assert p["opacity_logit"] is obj and opts["opacity_logit"].param_groups[0]["params"][0] is obj
    assert torch.all(torch.sigmoid(obj) <= 0.01 + 1e-6)
    assert torch.sigmoid(obj[0]) < 0.01 - 1e-4  # already below: untouched
    assert torch.all(opts["opacity_logit"].state[obj]["exp_avg"] == 0)


def _fake_info(n: int, grad_norm: torch.Tensor, radii: torch.Tensor, width=64, height=64):
    means2d = torch.zeros(1, n, 2, requires_grad=True)
    # screen gradient so that the normalised norm equals grad_norm
    g = torch.zeros(1, n, 2)
    g[0, :, 0] = grad_norm / (0.5 * width)
    means2d.grad = g
    return {
        "means2d": means2d,
        "radii": radii.reshape(1, n, 1).expand(1, n, 2).int(),
        "width": width,
        "height": height,
        "n_cameras": 1,
    }


def test_strategy_clone_split_prune_on_schedule():
    mesh = plane(8)
    n = 30
    p = init_params(mesh, n, generator=torch.Generator().manual_seed(1))
    opts = build_optimizers(p, LRS)
    strat = DensifyStrategy(refine_start_iter=2, refine_every=2, refine_stop_iter=100, reset_every=1000)
    state = strat.initialize_state(extent=1.0)
    with torch.no_grad():
        p["log_scale"][:10] = math.log(0.005)  # small -> clone
        p["log_scale"][10:20] = math.log(0.05)  # large -> split
        p["log_scale"][20:] = math.log(0.005)
        p["opacity_logit"][25:] = -10.0  # transparent -> pruned
    grad = torch.zeros(n)
    grad[:20] = 1e-3  # high
    radii = torch.full((n,), 3)
    radii[15:20] = 0  # invisible in this view: no statistics
    info = _fake_info(n, grad, radii)
    out = strat.step_post_backward(p, opts, state, 1, info, mesh=mesh)
    assert out == {"cloned": 0, "split": 0, "pruned": 0, "reset": 0}
    assert torch.allclose(state["grad2d"][:15], torch.full((15,), 1e-3))
    # screen radii are kept as a fraction of max(width, height), as gsplat
    assert torch.all(state["count"][15:20] == 0) and torch.all(state["radii"][:15] == 3 / 64)
    out = strat.step_post_backward(p, opts, state, 2, _fake_info(n, grad, radii), mesh=mesh)
    assert out["cloned"] == 10 and out["split"] == 5 and out["pruned"] == 5
    assert p["face"].shape[0] == n + 10 + 5 - 5
    for k, o in opts.items():
        assert o.param_groups[0]["params"][0] is p[k]
        assert o.state.get(p[k]) is None or o.state[p[k]]["exp_avg"].shape == p[k].shape
    assert state["grad2d"].shape[0] == p["face"].shape[0] and torch.all(state["grad2d"] == 0)


def test_the_final_iteration_neither_refines_nor_resets():
    """A run ending on a refinement (or reset) step saves what it trained: new Gaussians or reset
    opacities that no iteration would train are not made."""
    mesh = plane(8)
    n = 30
    p = init_params(mesh, n, generator=torch.Generator().manual_seed(1))
    opts = build_optimizers(p, LRS)
    strat = DensifyStrategy(refine_start_iter=2, refine_every=2, refine_stop_iter=100, reset_every=2)
    state = strat.initialize_state(extent=1.0)
    with torch.no_grad():
        p["log_scale"][:] = math.log(0.005)
    before = {k: v.detach().clone() for k, v in p.items()}
    grad = torch.full((n,), 1e-3)
    radii = torch.full((n,), 3)
    strat.step_post_backward(p, opts, state, 1, _fake_info(n, grad, radii), mesh=mesh)
    out = strat.step_post_backward(p, opts, state, 2, _fake_info(n, grad, radii), mesh=mesh, final=True)
    assert out == {"cloned": 0, "split": 0, "pruned": 0, "reset": 0}
    assert all(torch.equal(p[k], before[k]) for k in before)
    out = strat.step_post_backward(p, opts, state, 2, _fake_info(n, grad, radii), mesh=mesh)  # not final: it does
    assert out["cloned"] == n and out["reset"] == 1


def test_screen_size_prune_is_a_fraction_of_the_image_size():
    """After the first opacity reset, Gaussians wider than prune_scale2d * max(width, height) go."""
    mesh = plane(8)
    n = 10
    p = init_params(mesh, n, generator=torch.Generator().manual_seed(3))
    opts = build_optimizers(p, LRS)
    strat = DensifyStrategy(
        refine_start_iter=1,
        refine_every=4,
        reset_every=2,
        grow_grad2d=1.0,
        prune_opa=0.0,
        prune_scale2d=0.15,
        prune_scale3d=100.0,
    )
    state = strat.initialize_state(extent=1.0)
    radii = torch.full((n,), 20)  # 20 / 128 = 0.156 > 0.15 at 128 px wide
    radii[:6] = 19  # 19 / 128 = 0.148: kept
    grad = torch.zeros(n)
    for step in (1, 2, 3):
        strat.step_post_backward(p, opts, state, step, _fake_info(n, grad, radii, width=128, height=96), mesh=mesh)
    assert p["face"].shape[0] == n
    out = strat.step_post_backward(p, opts, state, 4, _fake_info(n, grad, radii, width=128, height=96), mesh=mesh)
    assert out["pruned"] == 4 and p["face"].shape[0] == 6


def test_split_children_land_on_surface():
    mesh = plane(8)
    n = 12
    p = init_params(mesh, n, generator=torch.Generator().manual_seed(2))
    with torch.no_grad():
        p["uv"].fill_(1 / 3)
        p["face"].copy_(torch.arange(n) * 5 + 20)  # interior faces
        p["log_scale"].copy_(torch.log(torch.tensor([0.04, 0.04, 1e-6])).expand(n, 3))
    parent = compose(p, MeshPose.canonical(mesh)).means.detach()
    opts = build_optimizers(p, LRS)
    strat = DensifyStrategy(refine_start_iter=1, refine_every=1, grow_scale3d=0.01)
    state = strat.initialize_state(1.0)
    torch.manual_seed(0)
    out = strat.step_post_backward(
        p, opts, state, 1, _fake_info(n, torch.full((n,), 1.0), torch.full((n,), 4)), mesh=mesh
    )
    assert out["split"] == n and p["face"].shape[0] == 2 * n
    assert torch.all(p["d"].abs() < 1e-4)  # flat parents on a flat mesh: children on the surface
    bary = torch.cat([p["uv"], 1 - p["uv"].sum(-1, keepdim=True)], -1)
    assert torch.all(bary > -1e-6)
    kids = compose(p, MeshPose.canonical(mesh)).means.detach()
    dist = (kids.reshape(2, n, 3) - parent[None]).norm(dim=-1)
    assert torch.all(dist < 5 * 0.04) and torch.any(dist > 1e-3)
    assert torch.allclose(p["log_scale"][:, 0], torch.full((2 * n,), math.log(0.04 / 1.6)), atol=1e-5)
    assert torch.all(p["duv"] == 0)


def test_budget_caps_growth():
    mesh = plane(8)
    n = 30
    p = init_params(mesh, n, generator=torch.Generator().manual_seed(3))
    opts = build_optimizers(p, LRS)
    with torch.no_grad():
        p["log_scale"].fill_(math.log(0.001))
    strat = DensifyStrategy(refine_start_iter=1, refine_every=1, max_gaussians=36)
    state = strat.initialize_state(1.0)
    grad = torch.linspace(1e-3, 2e-3, n)
    strat.step_post_backward(p, opts, state, 1, _fake_info(n, grad, torch.full((n,), 2)), mesh=mesh)
    assert p["face"].shape[0] == 36


def test_walk_moves_across_faces_and_resets_moments():
    mesh = plane(4)
    n = 20
    p = init_params(mesh, n, generator=torch.Generator().manual_seed(4))
    opts = build_optimizers(p, LRS)
    loss = (p["duv"] ** 2).sum() + (p["d"] ** 2).sum() + p["duv"].sum() + p["d"].sum()
    loss.backward()
    for o in opts.values():
        o.step()
    with torch.no_grad():
        p["duv"].zero_()
        p["duv"][:10] = torch.tensor([0.9, -0.3])  # far enough to leave the start face
    before = compose(p, MeshPose.canonical(mesh)).means.detach()
    duv_obj, d_obj, face_obj, uv_obj = p["duv"], p["d"], p["face"], p["uv"]
    face0 = p["face"].clone()
    d_m_before = opts["d"].state[d_obj]["exp_avg"].clone()
    changed = walk_embeddings(p, opts, mesh, mode="unfold")
    assert p["duv"] is duv_obj and p["d"] is d_obj and p["face"] is face_obj and p["uv"] is uv_obj
    assert opts["duv"].param_groups[0]["params"][0] is duv_obj and opts["d"].param_groups[0]["params"][0] is d_obj
    assert changed[:10].any() and not changed[10:].any()
    assert torch.equal(changed, p["face"] != face0)
    assert torch.all(p["duv"] == 0)
    assert torch.all(opts["duv"].state[duv_obj]["exp_avg"] == 0)
    d_m = opts["d"].state[d_obj]["exp_avg"]
    assert torch.all(d_m[changed] == 0) and torch.equal(d_m[~changed], d_m_before[~changed])
    after = compose(p, MeshPose.canonical(mesh)).means.detach()
    inside = ((before[:, :2] >= 0) & (before[:, :2] <= 1)).all(-1)  # unfolding on a plane is exact
    assert torch.allclose(after[inside], before[inside], atol=1e-5)


def test_walk_disabled_clips_to_triangle():
    mesh = plane(4)
    p = init_params(mesh, 20, generator=torch.Generator().manual_seed(5))
    opts = build_optimizers(p, LRS)
    with torch.no_grad():
        p["duv"].copy_(torch.randn(20, 2))
    face0 = p["face"].clone()
    changed = walk_embeddings(p, opts, mesh, walk=False)
    assert not changed.any() and torch.equal(p["face"], face0)
    bary = torch.cat([p["uv"], 1 - p["uv"].sum(-1, keepdim=True)], -1)
    assert torch.all(bary >= -1e-6) and torch.all(p["duv"] == 0)


def test_strategy_requires_mesh_to_refine():
    mesh = plane(2)
    p = init_params(mesh, 5)
    strat = DensifyStrategy(refine_start_iter=1, refine_every=1)
    state = strat.initialize_state(1.0)
    from meshsplat.errors import MeshsplatError

    with pytest.raises(MeshsplatError, match="mesh"):
        strat.step_post_backward(p, {}, state, 1, _fake_info(5, torch.ones(5), torch.ones(5)))
