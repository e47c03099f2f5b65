"""What the CPU kernels' vector code is worth, and what LLVM makes of them on this host (issue 47, arm64).

``--kernels lanes`` (the compositing lane kernels, float32) and ``projection`` (the one-camera projection kernels,
float64 arithmetic over Gaussians; ``numba_projection.projection_llvm_options``).

For each vector width (LLVM's ``-force-vector-width``; 1 = no vector code, ``host`` = meshsplat's rule,
``numba_lanes.lane_vector_width``): the packed floating-point instructions of the forward and backward lane
kernels (``numba_lanes.vector_report``) and, unless ``--codegen-only``, their CPU time on one thread (median of
``--repeats`` calls, fresh outputs each call) on the ``avatar_scene`` at the demo's size (20k @ 256²) and the
issue's (50k @ 512²). The contribution lists of every width are checked against the host's kernels.

Under an emulator (``qemu-aarch64``) only the code means anything: run it with ``--codegen-only`` (and
``NUMBA_CPU_NAME=apple-m1`` etc. for a target CPU). Prints a table, saves JSON.

For the projection the cases are 50k and 500k Gaussians @ 512², one camera, and the widths those of
``--projection-widths`` (default 1,2,4,host).

Usage: python bench/lane_width.py [--kernels lanes,projection] [--widths 1,4,8,host] [--projection-widths 1,2,4,host]
                                  [--repeats 15] [--codegen-only] [--out PATH]
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from functools import partial
from pathlib import Path

import numpy as np
import torch

from _machine import machine_info, results_path
from _raster_scenes import avatar_scene, binned_geometry

CASES = ((20_000, 256), (50_000, 512))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--kernels", default="lanes,projection")
    ap.add_argument("--widths", default="1,4,8,host")
    ap.add_argument("--projection-widths", default="1,2,4,host")
    ap.add_argument("--repeats", type=int, default=15)
    ap.add_argument("--codegen-only", action="store_true", help="count the packed instructions, time nothing")
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()

    import numba

    from meshsplat._numba import llvm_options
    from meshsplat.render.backends import numba_cpu as nc
    from meshsplat.render.backends import numba_lanes as nl

    torch.set_num_threads(1)
    numba.set_num_threads(1)
    nl.compile_kernels(numba)
    host = nl.lane_vector_width()
    widths = [host if w == "host" else int(w) for w in args.widths.split(",")]
    rows = []
    kernels = args.kernels.split(",")
    for n, size in (CASES[:1] if args.codegen_only else CASES) if "lanes" in kernels else ():
        scene = avatar_scene(n, size, seed=0)
        geo, bg = binned_geometry(scene), scene["backgrounds"].contiguous().numpy()
        fargs = geo.args(bg)
        ntile = fargs[3].shape[0]
        out, t_final, n_contrib, _ = nc._kernels().forward_lanes(*fargs)  # the host's kernels: the reference
        bargs = (*fargs, np.ones_like(out), np.ones(t_final.shape[0], out.dtype), t_final, n_contrib)
        for width in dict.fromkeys(widths):  # each width once
            o = nl._outputs(fargs[2], fargs[4], fargs[5], fargs[8], fargs[9])
            code = {"forward": nl.vector_report(fargs, width=width),
                    "backward": nl.vector_report(bargs, backward=True, width=width)}  # fmt: skip
            row = {"kernels": "lanes", "case": f"{n // 1000}k @ {size}²", "width": width, "host_rule": width == host,
                   "code": code}  # fmt: skip
            if not args.codegen_only:
                njit = numba.njit(cache=False, nogil=True, error_model="numpy")
                fw, bw = njit(nl._forward_lanes), njit(nl._backward_lanes)
                with llvm_options({"force-vector-width": width} if width else {}):
                    fw(*fargs, *o, 0, ntile)
                    bw(*bargs, nl.grad_rows(fargs[1], fargs[2]), 0, ntile)
                row["same_lists"] = bool(np.array_equal(o[2], n_contrib))
                row.update(_timed(
                    args.repeats,
                    (fw, fargs, partial(nl._outputs, fargs[2], fargs[4], fargs[5], fargs[8], fargs[9]), (0, ntile)),
                    (bw, bargs, partial(_one, nl.grad_rows, fargs[1], fargs[2]), (0, ntile)),
                ))  # fmt: skip
            rows.append(row)
            _print_row(row, host, f"same lists {row.get('same_lists')}")
    if "projection" in kernels:
        rows += _projection(args, numba)

    out = args.out or results_path("lane_width")
    out.write_text(json.dumps({"machine": {**machine_info(), "arch": platform.machine(), "numba": numba.__version__,
                                           "numba_cpu_name": numba.config.CPU_NAME or None},
                               "host_width": host, "codegen_only": args.codegen_only, "rows": rows}, indent=1))  # fmt: skip
    print(f"wrote {out}")


def _one(make, *args) -> tuple:
    """``(make(*args),)``: one output array as the tuple ``_timed`` spreads."""
    return (make(*args),)


def _timed(repeats: int, forward: tuple, backward: tuple) -> dict[str, float]:
    """Median CPU milliseconds of each ``(kernel, head, outputs, tail)``: ``kernel(*head, *outputs(), *tail)``, fresh
    outputs each call."""
    times: dict[str, list[float]] = {"forward_ms": [], "backward_ms": []}
    for _ in range(repeats):
        for key, (kernel, head, outputs, tail) in zip(times, (forward, backward), strict=True):
            o = outputs()
            t = time.process_time()
            kernel(*head, *o, *tail)
            times[key].append(time.process_time() - t)
    return {key: 1e3 * float(np.median(v)) for key, v in times.items()}


def _print_row(row: dict, host: int, check: str) -> None:
    packed = {pass_: {reg: c for reg, c in v.items() if c} for pass_, v in row["code"].items()}
    timing = (
        f"forward {row['forward_ms']:7.2f} ms  backward {row['backward_ms']:7.2f} ms  " if "forward_ms" in row else ""
    )
    host_mark = " (host)" if row["width"] == host else "       "
    print(f"{row['kernels']} {row['case']:>11}  width {row['width']:2d}{host_mark}  {timing}{check}  packed {packed}",
          flush=True)  # fmt: skip


PROJECTION_CASES = ((50_000, 512), (500_000, 512))
NEAR, FAR = 0.01, 1e10


def _packed_float64(asm: str) -> dict[str, int]:
    """Packed float64 arithmetic in ``asm``: x86-64 ``v...pd`` by register, arm64 ``f...`` on ``v0.2d``."""
    import re

    x86 = re.findall(r"^\s*v(?:add|sub|mul|div|min|max|sqrt|fmadd[0-9]*)pd\s+([^\n]*)", asm, re.M)
    report = {reg: sum(f"%{reg}" in ops for ops in x86) for reg in ("zmm", "ymm", "xmm")}
    report["neon"] = len(re.findall(r"^\s*f[a-z]+\s+v\d+\.2d", asm, re.M))
    return report


def _projection(args, numba) -> list[dict]:
    """The one-camera projection kernels, forward and backward, at each of ``--projection-widths``."""
    from meshsplat._numba import llvm_options
    from meshsplat.render.backends import numba_cpu as nc
    from meshsplat.render.backends import numba_projection as P

    nc._kernels()  # the projection's inlined helpers bound
    options = P.projection_llvm_options()
    host = options["force-vector-width"]
    widths = [host if w == "host" else int(w) for w in args.projection_widths.split(",")]
    rows = []
    for n, size in PROJECTION_CASES[:1] if args.codegen_only else PROJECTION_CASES:
        s = avatar_scene(n, size, seed=0)
        flat = [s[k].contiguous().numpy().reshape(-1) for k in ("means", "quats", "scales", "opacities")]
        cam = P._camera_vector(s["viewmats"][:1].double().numpy(), s["Ks"][:1].double().numpy(), float(size),
                               float(size))  # fmt: skip
        f32 = np.float32
        reference = None
        for width in dict.fromkeys(widths):
            njit = numba.njit(cache=False, nogil=True, error_model="numpy")
            fwd, bwd = njit(P._project_one_kernel), njit(P._project_one_backward_kernel)

            def outputs(n=n, f32=f32):
                return (np.zeros(2 * n, f32), np.zeros(3 * n, f32), np.zeros(n, f32), np.zeros(2 * n, np.int32),
                        np.zeros(n, np.bool_))  # fmt: skip

            grads = (np.ones(2 * n, f32), np.ones(3 * n, f32), np.ones(n, f32))

            def g_outputs(n=n, f32=f32):
                return np.zeros(3 * n, f32), np.zeros(4 * n, f32), np.zeros(3 * n, f32)

            outs = outputs()
            with llvm_options(dict(options, **{"force-vector-width": width})):
                fwd(*flat, cam, float(size), float(size), NEAR, FAR, *outs, 0, n)
                bwd(*flat[:3], cam, outs[4], *grads, *g_outputs(), 0, n)
            code = {"forward": _packed_float64("\n".join(fwd.inspect_asm().values())),
                    "backward": _packed_float64("\n".join(bwd.inspect_asm().values()))}  # fmt: skip
            if reference is None:
                reference = outs
            row = {"kernels": "projection", "case": f"{n // 1000}k @ {size}²", "width": width,
                   "host_rule": width == host, "code": code,
                   "same_bits": all(np.array_equal(a, b) for a, b in zip(outs, reference, strict=True))}  # fmt: skip
            if not args.codegen_only:
                row.update(_timed(
                    args.repeats,
                    (fwd, (*flat, cam, float(size), float(size), NEAR, FAR), outputs, (0, n)),
                    (bwd, (*flat[:3], cam, outs[4], *grads), g_outputs, (0, n)),
                ))  # fmt: skip
            rows.append(row)
            _print_row(row, host, f"same bits {row['same_bits']}")
    return rows


if __name__ == "__main__":
    main()
