"""The albedo prior (albedo_prior.weight): neighbours, the prior's value and gradient, training and resume."""

from __future__ import annotations

import shutil

import pytest
import torch
import trimesh

import meshsplat.train.components.albedo_prior as trainer_module
from _train_kit import small_config
from meshsplat._numba import numba_available
from meshsplat.embedding import surface_points
from meshsplat.errors import MeshsplatError
from meshsplat.gaussians import rgb_to_sh0
from meshsplat.io.checkpoint import load_checkpoint
from meshsplat.train import Trainer
from meshsplat.train.albedo_prior import MAX_REACH, NEIGHBOURS, albedo_neighbours, albedo_smoothness, neighbour_ranks

needs_numba = pytest.mark.skipif(not numba_available(), reason="the compiled prior needs numba (the fast extra)")
PATHS = [pytest.param(False, id="torch"), pytest.param(True, id="numba", marks=needs_numba)]


def _sphere_embedding(n: int, seed: int = 0):
    m = trimesh.creation.icosphere(subdivisions=2)
    verts, faces = torch.tensor(m.vertices, dtype=torch.float32), torch.tensor(m.faces).long()
    g = torch.Generator().manual_seed(seed)
    face = torch.randint(0, faces.shape[0], (n,), generator=g)
    uv = torch.rand(n, 2, generator=g) * 0.5  # u + v <= 1: inside the triangle
    return verts, faces, face, uv


def test_neighbours_are_the_nearest_others_on_the_mesh():
    verts, faces, face, uv = _sphere_embedding(300)
    nb = albedo_neighbours(verts, faces, face, uv)
    assert nb.shape == (300, NEIGHBOURS) and nb.dtype == torch.long
    pts = surface_points(verts, faces, face, uv).double()
    d = torch.cdist(pts, pts)
    d.fill_diagonal_(float("inf"))
    brute = d.topk(NEIGHBOURS, largest=False).indices
    assert torch.equal(nb, brute)  # nearest first, the same order
    assert not (nb == torch.arange(300)[:, None]).any()
    assert torch.equal(nb, albedo_neighbours(verts, faces, face, uv))  # deterministic


def test_a_reach_adds_farther_neighbours_spread_by_rank():
    verts, faces, face, uv = _sphere_embedding(300)
    assert neighbour_ranks(NEIGHBOURS).tolist() == list(range(1, NEIGHBOURS + 1))
    assert neighbour_ranks(64).tolist() == list(range(1, 9)) + [9, 17, 25, 33, 40, 48, 56, 64]
    nb = albedo_neighbours(verts, faces, face, uv, 64)
    assert nb.shape == (300, 2 * NEIGHBOURS)
    pts = surface_points(verts, faces, face, uv).double()
    d = torch.cdist(pts, pts)
    d.fill_diagonal_(float("inf"))
    order = d.argsort(dim=1)  # by rank: column r - 1 is the r-th nearest other
    assert torch.equal(nb, order[:, torch.from_numpy(neighbour_ranks(64)) - 1])
    assert torch.equal(nb[:, :NEIGHBOURS], albedo_neighbours(verts, faces, face, uv))  # the nearest, as reach 8
    for bad in (NEIGHBOURS - 1, MAX_REACH + 1):
        with pytest.raises(MeshsplatError, match=rf"^albedo prior: reach must be in 8\.\.{MAX_REACH}, got {bad}$"):
            albedo_neighbours(verts, faces, face, uv, bad)
    few = albedo_neighbours(verts, faces, face[:20], uv[:20], 64)  # fewer Gaussians than the reach: repeats
    assert few.shape == (20, 2 * NEIGHBOURS) and not (few == torch.arange(20)[:, None]).any()


def test_neighbours_of_coincident_and_few_gaussians():
    verts, faces, face, uv = _sphere_embedding(40)
    face, uv = torch.cat([face, face[:5]]), torch.cat([uv, uv[:5]])  # 5 Gaussians at the same points as 5 others
    nb = albedo_neighbours(verts, faces, face, uv)
    assert not (nb == torch.arange(45)[:, None]).any()  # never itself, even where a twin sits at distance 0
    assert torch.equal(nb[:5, 0], torch.arange(40, 45)) and torch.equal(nb[40:, 0], torch.arange(5))
    three = albedo_neighbours(verts, faces, face[:3], uv[:3])
    assert three.shape == (3, NEIGHBOURS)
    for i in range(3):
        assert set(three[i].tolist()) == {0, 1, 2} - {i}
    assert albedo_neighbours(verts, faces, face[:1], uv[:1]).shape == (1, 0)
    assert albedo_smoothness(rgb_to_sh0(torch.rand(1, 3)), torch.zeros(1, 0, dtype=torch.long)) == 0


@pytest.mark.parametrize("compiled", PATHS)
def test_the_prior_pulls_one_hue_together_and_leaves_a_change_of_hue_alone(compiled):
    orange = torch.tensor([0.6, 0.3, 0.04])
    nb = torch.tensor([[1], [0], [3], [2]])  # pairs (0, 1) and (2, 3)
    # 0, 1: one orange in light and in shadow (one hue, another brightness); 2, 3: orange next to blue
    rgb = torch.stack([orange, 0.4 * orange, orange, torch.tensor([0.1, 0.2, 0.6])])
    sh0 = rgb_to_sh0(rgb).requires_grad_(True)
    value = albedo_smoothness(sh0, nb, compiled=compiled)
    (grad,) = torch.autograd.grad(value, sh0)
    same, edge = grad[:2, 0].abs().sum(), grad[2:, 0].abs().sum()
    assert same > 1e3 * edge  # the hue edge keeps a weight of exp(-|dc|^2 / sigma^2), here ~1e-12
    assert (grad[0, 0] > 0).all() and (grad[1, 0] < 0).all()  # the bright one darker, the dark one brighter
    one = rgb_to_sh0(orange.expand(4, 3))
    assert float(albedo_smoothness(one, nb, compiled=compiled)) == 0.0


@pytest.mark.parametrize("compiled", PATHS)
def test_the_prior_has_the_gradient_of_its_value(compiled):
    verts, faces, face, uv = _sphere_embedding(30, seed=2)
    nb = albedo_neighbours(verts, faces, face, uv)
    g = torch.Generator().manual_seed(3)
    # one hue in several brightnesses: the weights are 1 there and flat (they carry no gradient by design)
    rgb = torch.tensor([0.6, 0.3, 0.05]) * (0.5 + torch.rand(30, 1, generator=g))
    sh0 = rgb_to_sh0(rgb).double().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda s: albedo_smoothness(s, nb, compiled=compiled), (sh0,), eps=1e-7, atol=1e-6)


@needs_numba
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_the_compiled_prior_equals_the_torch_path(dtype):
    g = torch.Generator().manual_seed(7)
    n = 2000
    rgb = torch.rand(n, 3, generator=g, dtype=dtype)
    rgb[: n // 2] = torch.tensor([0.6, 0.3, 0.05], dtype=dtype) * (0.3 + rgb[: n // 2, :1])  # one hue: weights near 1
    rgb[:10] = rgb[10:20]  # equal albedos: abs's gradient is 0 there on both paths
    sh0 = rgb_to_sh0(rgb)
    nb = torch.randint(0, n, (n, 2 * NEIGHBOURS), generator=g)
    nb[:10, 0] = torch.arange(10, 20)
    out = []
    for compiled in (False, True):
        x = sh0.clone().requires_grad_(True)
        value = albedo_smoothness(x, nb, compiled=compiled)
        (grad,) = torch.autograd.grad(value, x)
        assert value.dtype == dtype and grad.dtype == dtype
        out.append((value.detach(), grad))
    tol = 1e-12 if dtype == torch.float64 else 1e-6
    torch.testing.assert_close(out[1][0], out[0][0], rtol=tol, atol=0)
    torch.testing.assert_close(out[1][1], out[0][1], rtol=tol, atol=tol * float(out[0][1].abs().max()))


@needs_numba
def test_the_compiled_weights_exp_is_libms_to_two_ulps():
    """The pair weights' polynomial ``exp`` against ``math.exp``: within 5e-16 relative down to -708, exactly 1 at
    0, 0 where libm's underflows to 0 (below -745), and exp(-708) in between (where libm's are subnormals)."""
    import math

    import numpy as np

    from meshsplat.train import _albedo_prior_numba as compiled_prior

    compiled_prior._kernels()
    exp = compiled_prior._exp
    xs = np.concatenate([-np.geomspace(1e-12, 708.0, 4000), -np.linspace(0.0, 1.0, 1001)])
    got = np.array([exp(float(x)) for x in xs])
    ref = np.array([math.exp(float(x)) for x in xs])
    assert float(np.max(np.abs(got - ref) / ref)) < 5e-16
    assert exp(0.0) == 1.0 and exp(-746.0) == 0.0 and exp(-1e300) == 0.0 and exp(-float("inf")) == 0.0
    assert exp(-720.0) == exp(-708.0) and abs(exp(-708.0) / math.exp(-708.0) - 1.0) < 5e-16


@pytest.mark.parametrize("compiled", PATHS)
def test_neighbours_out_of_range_are_refused_in_one_line(compiled):
    sh0 = rgb_to_sh0(torch.rand(5, 3))
    for bad in (5, -1):
        nb = torch.tensor([[1], [2], [3], [4], [bad]])
        with pytest.raises(MeshsplatError, match=r"neighbour indices must be in 0\.\.4"):
            albedo_smoothness(sh0, nb, compiled=compiled)


@pytest.mark.parametrize("compiled", PATHS)
def test_the_prior_and_its_gradient_repeat_bit_for_bit_on_several_threads(compiled):
    """A gather's backward that scatters with atomics (``a[neighbours]``) sums in another order on each call
    with 2 threads; the prior must not (training runs repeat to the last digit)."""
    g = torch.Generator().manual_seed(5)
    n = 12_000
    sh0 = rgb_to_sh0(torch.rand(n, 3, generator=g))
    nb = torch.randint(0, n, (n, NEIGHBOURS), generator=g)
    threads = torch.get_num_threads()
    try:
        results = []
        for k in range(6):
            torch.set_num_threads(2 if k < 5 else 1)  # the compiled path is the same on any thread count
            x = sh0.clone().requires_grad_(True)
            value = albedo_smoothness(x, nb, compiled=compiled)
            (grad,) = torch.autograd.grad(value, x)
            results.append((value.detach(), grad))
    finally:
        torch.set_num_threads(threads)
    if not compiled:
        results.pop()  # the torch path's sums are split by thread
    for value, grad in results[1:]:
        assert torch.equal(value, results[0][0]) and torch.equal(grad, results[0][1])


def test_training_with_the_prior_keeps_its_neighbours_and_resumes_bit_exact(tiny_dataset, tmp_path, monkeypatch):
    monkeypatch.setattr(trainer_module, "REFRESH_EVERY", 3)  # neighbours searched again within the run
    seen: list[int] = []
    search = trainer_module.albedo_neighbours

    def counted(*args):
        nb = search(*args)
        seen.append(int(nb.shape[0]))
        return nb

    monkeypatch.setattr(trainer_module, "albedo_neighbours", counted)
    extra = ("albedo_prior.weight=0.5", "checkpoint_every=4")
    full = Trainer(small_config(tiny_dataset, tmp_path / "full", 20, extra))
    assert full.cfg.shading.enabled
    full.train()
    assert len(seen) >= 7  # every third iteration, and when densification changed the count
    # resume from every checkpoint: some written just after a densification, whose neighbours still index the
    # Gaussians before it (searched again at the next step, as in the full run), some not
    stale = [
        it
        for it in (4, 8, 12, 16)
        if (st := load_checkpoint(tmp_path / "full" / "checkpoints" / f"ckpt_{it:08d}.pt"))["components"][
            "albedo_prior"
        ]["neighbours"].shape[0]
        != st["avatar"]["params"]["sh0"].shape[0]
    ]
    assert stale and stale != [4, 8, 12, 16], stale  # both kinds are resumed below
    for start in (4, 8, 12, 16):
        run = tmp_path / f"resumed{start}"
        (run / "checkpoints").mkdir(parents=True)
        shutil.copy(tmp_path / "full" / "checkpoints" / f"ckpt_{start:08d}.pt", run / "checkpoints")
        res = Trainer(small_config(tiny_dataset, run, 20, extra), resume=True)
        assert res.component("albedo_prior").neighbours is not None and res.iteration == start
        res.train()
        for k in full.params:
            assert torch.equal(full.params[k].detach(), res.params[k].detach()), (start, k)
        assert torch.equal(full.component("albedo_prior").neighbours, res.component("albedo_prior").neighbours)
    # without the prior the same run trains to other colours
    off = Trainer(small_config(tiny_dataset, tmp_path / "off", 20, ("albedo_prior.weight=0",)))
    off.train()
    assert off.component("albedo_prior").neighbours is None and not torch.equal(off.params["sh0"], full.params["sh0"])


def test_a_checkpoint_with_damaged_neighbours_is_refused_in_one_line(tiny_dataset, tmp_path):
    cfg = small_config(tiny_dataset, tmp_path / "run", 10)
    Trainer(cfg).train()
    path = tmp_path / "run" / "checkpoints" / "ckpt_00000010.pt"
    doc = torch.load(path, weights_only=True)
    prior = doc["state"]["components"]["albedo_prior"]
    assert prior["neighbours"].shape[1] == 2 * NEIGHBOURS  # the nearest and as many farther (albedo_prior.reach)
    prior["neighbours"][3, 2] = prior["neighbours"].shape[0]  # past the last Gaussian
    torch.save(doc, path)
    with pytest.raises(MeshsplatError, match=r"^checkpoint: its albedo prior's neighbours are not indices of its"):
        Trainer(cfg, resume=True)
