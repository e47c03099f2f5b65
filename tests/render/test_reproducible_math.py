"""``import meshsplat`` makes torch's MKL math reproducible run to run (``MKL_CBWR``), which bit-exact
resume relies on: without it a convolution's backward on 1 x 1 maps (LPIPS of a small crop) can differ in
the last bit between two calls on the same numbers, depending on where its buffers happen to lie."""

from __future__ import annotations

import os
import subprocess
import sys

# In a fresh interpreter (MKL reads the setting once): meshsplat first, then 30 backward passes of the
# same convolution on the same numbers, each on freshly allocated buffers; prints the setting and how many
# distinct input gradients came out.
PROBE = """
import hashlib, os
import meshsplat
import torch
torch.set_num_threads(2)
g = torch.Generator().manual_seed(0)
w = torch.randn(384, 192, 3, 3, generator=g)
x0, go = torch.randn(1, 192, 1, 1, generator=g), torch.randn(1, 384, 1, 1, generator=g)
grads = set()
for _ in range(30):
    x = x0.clone().requires_grad_(True)
    torch.nn.functional.conv2d(x, w, padding=1).backward(go)
    grads.add(hashlib.md5(x.grad.numpy().tobytes()).hexdigest())
print(os.environ["MKL_CBWR"] + "|" + str(len(grads)))
"""


def _probe(**env: str) -> tuple[str, int]:
    base = {k: v for k, v in os.environ.items() if k != "MKL_CBWR"}
    out = subprocess.run([sys.executable, "-c", PROBE], env={**base, **env}, capture_output=True, text=True, check=True)
    setting, n = out.stdout.strip().rsplit("|", 1)
    return setting, int(n)


def test_importing_meshsplat_makes_the_convolution_backward_reproducible():
    assert _probe() == ("AUTO,STRICT", 1)


def test_a_users_own_mkl_setting_wins():
    setting, n = _probe(MKL_CBWR="COMPATIBLE")
    assert (setting, n) == ("COMPATIBLE", 1)
    assert _probe(MKL_CBWR="")[0] == ""  # empty: MKL's default, left alone
