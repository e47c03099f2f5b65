"""Reading a capture at 1/N of its size (`--downscale N`, `open_capture(..., downscale=N)`): the golden
capture at 64x64 read at 32x32 (area-averaged images, K such that points land on half the image
coordinates, pixel centres at +0.5 as the rasterizer samples them), every layout, the run remembering
its setting for eval, import writing it, and absurd factors refused in one line."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from _capture_kit import K64, _capture
from _peoplesnapshot import make_capture
from meshsplat.cli.main import main
from meshsplat.data import open_dataset
from meshsplat.data.downscale import area_resize, downscaled_size
from meshsplat.data.formats import open_capture
from meshsplat.errors import MeshsplatError
from meshsplat.render import rasterize
from meshsplat.run_folder import load_run


def _pool(x: torch.Tensor) -> torch.Tensor:
    """2x2 mean of ``[H,W,C]`` (the area resize of an integer factor 2)."""
    return F.avg_pool2d(x.permute(2, 0, 1)[None].double(), 2)[0].permute(1, 2, 0)


def test_golden_64_read_at_32(tmp_path):
    root = _capture(tmp_path / "cap")
    full, half = open_dataset(root), open_dataset(root, downscale=2)
    cam, cam2 = full.camera("0"), half.camera("0")
    assert (cam2.width, cam2.height) == (32, 32)
    assert torch.allclose(cam2.K, torch.tensor([[40.0, 0, 15.65], [0, 37.5, 16.55], [0, 0, 1]]))
    assert torch.equal(cam2.viewmat, cam.viewmat)
    # a known 3D point lands on exactly half the image coordinates
    X = torch.tensor([0.31, -0.22, 0.4, 1.0])
    uvw64, uvw32 = cam.K @ (cam.viewmat @ X)[:3], cam2.K @ (cam2.viewmat @ X)[:3]
    assert torch.allclose(uvw32[:2] / uvw32[2], 0.5 * uvw64[:2] / uvw64[2], atol=1e-5)
    # frame without a mask: its image is the 2x2 area mean of the original
    f, f2 = full[5], half[5]
    assert f2.mask is None and f2.image.shape == (32, 32, 3) and f2.image.dtype == torch.float32
    assert torch.allclose(f2.image.double(), _pool(f.image), atol=1e-6)
    assert f2.camera.K.tolist() == cam2.K.tolist() and half.frame_camera(5).width == 32
    # frame with a mask: soft mask = area mean; its composite over any colour = area mean of the full composite
    f, f2 = full[1], half[1]
    assert torch.allclose(f2.mask.double(), _pool(f.mask), atol=1e-6)
    assert set(np.unique(f2.mask.numpy())) == {0.0, 0.5, 1.0}  # soft at the edge, as training uses it
    for bg in (torch.zeros(3), torch.ones(3), torch.tensor([0.2, 0.7, 0.4])):
        c2 = f2.image * f2.mask + bg * (1 - f2.mask)
        c = f.image * f.mask + bg * (1 - f.mask)
        assert torch.allclose(c2.double(), _pool(c), atol=1e-6)
    inside = f2.mask[..., 0] == 1  # fully covered pixels: plain area mean
    assert torch.allclose(f2.image[inside].double(), _pool(f.image)[inside], atol=1e-6)


def test_downscaled_K_matches_the_rasterizer_pixel_centres():
    """A small Gaussian rendered at 64x64 and, with the scaled K, at 32x32: its centroid (pixel centres
    at +0.5) sits on the projected point and halves exactly; a half-pixel slip would show."""
    from meshsplat.data.downscale import scale_intrinsics

    mean = torch.tensor([[-0.4, -0.3, 3.0]])
    cents = []
    for size in (64, 32):
        K = torch.tensor(scale_intrinsics(K64, 64, 64, size, size), dtype=torch.float32)
        out = rasterize(
            mean,
            torch.tensor([[1.0, 0, 0, 0]]),
            torch.full((1, 3), 0.2),
            torch.ones(1),
            torch.ones(1, 3),
            torch.eye(4)[None],
            K[None],
            size,
            size,
            backend="torch",
        )
        a = out.alphas[0, ..., 0].double()
        ys, xs = torch.meshgrid(torch.arange(size) + 0.5, torch.arange(size) + 0.5, indexing="ij")
        cents.append(torch.stack([(a * xs).sum() / a.sum(), (a * ys).sum() / a.sum()]))
        proj = K.double() @ mean[0].double()
        assert torch.allclose(cents[-1], proj[:2] / proj[2], atol=0.02)
    assert torch.allclose(cents[1], cents[0] / 2, atol=0.02)


def test_non_divisible_sizes_and_fractional_factors(tmp_path):
    root = _capture(tmp_path / "odd", size=(65, 47), n=3)
    full = open_dataset(root)
    for factor, size in ((2, (33, 24)), (1.5, (43, 31)), (3, (22, 16))):
        assert downscaled_size(65, 47, factor) == size
        ds = open_dataset(root, downscale=factor)
        cam = ds.camera("0")
        assert (cam.width, cam.height) == size
        expect = K64.copy()
        expect[0] *= size[0] / 65
        expect[1] *= size[1] / 47
        assert np.allclose(cam.K.numpy(), expect, atol=1e-5)
        img = ds[2].image  # no mask: a plain box filter, which keeps the image's mean exactly
        assert img.shape == (size[1], size[0], 3)
        assert torch.allclose(img.double().mean((0, 1)), full[2].image.double().mean((0, 1)), atol=1e-6)
    x = torch.rand(9, 7, 2, dtype=torch.float64)
    assert torch.allclose(area_resize(x, 7, 9), x)  # factor 1 changes nothing


@pytest.mark.parametrize("bad", [0, -2, 0.5, 65, float("nan"), float("inf"), True, "2"])
def test_absurd_factors_are_one_line(tmp_path, bad):
    root = _capture(tmp_path / "cap", n=2)
    with pytest.raises(MeshsplatError, match="downscale") as info:
        open_dataset(root, downscale=bad)
    assert "\n" not in str(info.value)


def test_every_layout_reads_downscaled(tmp_path, standin_model_dir, capsys):
    root = make_capture(tmp_path / "ps", n=6)  # PeopleSnapshot, 64x48
    ds = open_capture(root, model_dir=standin_model_dir, downscale=2)
    assert ds.format_name == "peoplesnapshot"
    cam = ds.frame_camera(0)
    assert (cam.width, cam.height) == (32, 24)
    # the file's integer-centre cx, cy = 32, 24 read as 32.5, 24.5 (meshsplat's half-pixel centres), then halved
    assert cam.K[:2].tolist() == [[50.0, 0.0, 16.25], [0.0, 50.0, 12.25]]
    fr = ds[0]
    assert fr.image.shape == (24, 32, 3) and fr.mask.shape == (24, 32, 1)
    full = open_capture(root, model_dir=standin_model_dir)[0]
    assert torch.allclose(fr.mask.double(), _pool(full.mask), atol=1e-6)
    with pytest.raises(MeshsplatError, match=r"larger than the 64x48 image of camera '0' \(at most 48\)"):
        open_capture(root, model_dir=standin_model_dir, downscale=49)
    out = tmp_path / "x"
    args = ["import", str(root), "--out", str(out), "--model-dir", str(standin_model_dir), "--downscale", "0"]
    assert main(args) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("meshsplat import: error: downscale: expected a factor >= 1") and "\n" not in err


def test_import_writes_the_downscaled_native_dataset(tmp_path, capsys):
    root = _capture(tmp_path / "cap")
    out = tmp_path / "native"
    assert main(["import", str(root), "--out", str(out), "--downscale", "2"]) == 0
    assert "downscale 2: images written at 32x32, K scaled to match" in capsys.readouterr().out
    nat, half = open_dataset(out), open_dataset(root, downscale=2)
    assert nat.meta["downscale"] == 2.0 and nat.downscale == 1.0
    assert torch.allclose(nat.camera("0").K, half.camera("0").K)
    for i in (1, 5):
        a, b = nat[i], half[i]
        assert a.image.shape == (32, 32, 3)
        assert (a.image - b.image).abs().max() <= 0.5 / 255 + 1e-6  # PNG quantisation only
        assert (a.mask is None) == (b.mask is None)
        if a.mask is not None:
            assert (a.mask - b.mask).abs().max() <= 0.5 / 255 + 1e-6


def test_train_and_eval_keep_the_runs_downscale(tmp_path, capsys):
    root = _capture(tmp_path / "cap")
    run = tmp_path / "run"
    args = ["train", str(root), "--out", str(run), "--downscale", "2", "--iters", "3", "--device", "cpu"]
    assert main([*args, "--no-progress", "--set", "model.n_init=200", "loss.lambda_lpips=0"]) == 0
    assert "training images 32x32" in capsys.readouterr().out
    assert json.loads((run / "config.json").read_text())["data_downscale"] == 2.0
    assert load_run(run).open_dataset().frame_camera(0).width == 32  # render and view read the same size
    assert main(["eval", str(run), "--no-lpips", "--no-report", "--device", "cpu", "--no-progress"]) == 0
    m = json.loads((run / "eval" / "metrics.json").read_text())
    assert m["downscale"] == 2.0 and m["splits"]["test_frames"]["n_frames"] == 2
    assert main(["eval", str(run), "--no-lpips", "--no-report", "--downscale", "1", "--out", str(tmp_path / "e1")]) == 0
    assert json.loads((tmp_path / "e1" / "metrics.json").read_text())["downscale"] == 1.0
    assert main(["eval", str(run), "--no-report", "--downscale", "-1", "--out", str(tmp_path / "e2")]) == 2
    assert "downscale: expected a factor >= 1" in capsys.readouterr().err
