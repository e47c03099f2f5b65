"""Benchmark the player's splat draw in headless Chromium (SwiftShader WebGL2, the GPU work on this CPU):
the page of today against the page of ``--before-rev`` (its viewer.js in the same bundle), in the same
run, alternating pages over ``--rounds`` rounds.

A time is the page's ``timeDraws``: the current frame drawn again, each draw waited for by a 1-pixel
readback (the splat pass(es), the draw call, the float target's clamp pass; no posing passes, no
sort); the first draw of each call is left out (an older page's ``timeDraws`` left its last draw
unwaited, which the next call's first time paid for). Cases: random shaded avatars (SH degree 1,
learned irradiance) on CesiumMan's vertex frames at 20k and 100k Gaussians, and with ``--avatar RUN``
a trained blend-shape head as ``meshsplat view RUN --animation blendshapes`` writes it; each at the
sizes of ``--sizes`` (CSS pixels at device ratio 1: the drawing buffer), 258x193 being the webcam
mode's capped buffer in a 640x480 page.

Usage: python bench/viewer_draw.py [--avatar RUN] [--rounds 2] [--draws 6] [--sizes 258x193,640x480]
                                    [--before-rev 8929a54] [--out bench/results/viewer_draw-<host>.json]
"""

from __future__ import annotations

import argparse
import json
import shutil
import statistics
import sys
import tempfile
from pathlib import Path

import torch

from _machine import machine_info, results_path
from meshsplat.viewer import write_viewer_bundle
from viewer import cesium, page_code, page_code_at, random_avatar, require_sparse_rigs

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))  # the headless-Chromium driver the browser tests use
from _browser import find_chromium, open_page  # noqa: E402


def time_page(index: Path, size: tuple[int, int], draws: int, chromium: str) -> list[float]:
    with open_page(index.as_uri() + "?ui=0&play=0", *size, chromium) as page:
        page.wait_ready(300)
        page.evaluate("window.meshsplatViewer.timeDraws(2)")  # warm-up
        return page.evaluate(f"window.meshsplatViewer.timeDraws({draws + 1})")[1:]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--avatar", type=Path, default=None, help="a trained blend-shape head's run folder")
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--draws", type=int, default=6, help="draws timed per page and round")
    ap.add_argument("--sizes", default="258x193,640x480")
    ap.add_argument("--random", default="20000,100000", help="random avatars' Gaussian counts ('' for none)")
    ap.add_argument("--before-rev", default="8929a54")
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    chromium = find_chromium()
    if chromium is None:
        sys.exit("chromium is not installed")
    torch.set_num_threads(1)
    old_js = page_code_at(args.before_rev)
    if args.avatar is not None:  # a blend-shape head, written by today's writer for both pages
        require_sparse_rigs(old_js, args.before_rev)
    sizes = [tuple(int(x) for x in s.split("x")) for s in args.sizes.split(",")]
    work = Path(tempfile.mkdtemp(prefix="meshsplat-draw-bench-"))
    pages: dict[str, dict[str, Path]] = {}  # case -> {before, now} -> index.html
    try:
        if args.random:
            mesh, frames = cesium(30)
            for n in (int(x) for x in args.random.split(",")):
                av = random_avatar(mesh, n, shaded=True)
                case = f"random shaded, {n:,} Gaussians"
                pages[case] = {}
                for code, js in (("before", old_js), ("now", None)):
                    out = work / f"r{n}-{code}"
                    with page_code(js):
                        write_viewer_bundle(av, frames[20:21], out)
                    pages[case][code] = out / "index.html"
        if args.avatar is not None:
            from meshsplat.cli.main import main as cli

            head = json.loads((args.avatar / "config.json").read_text()).get("data", "")
            case = f"trained head ({args.avatar.name} of {Path(head).name})"
            pages[case] = {}
            for code, js in (("before", old_js), ("now", None)):
                out = work / f"head-{code}"
                argv = ["view", str(args.avatar), "--animation", "blendshapes", "--frames", "1", "--out", str(out)]
                with page_code(js):
                    cli(argv)
                pages[case][code] = out / "index.html"
        rows = []
        for case, by_code in pages.items():
            gaussians = json.loads((by_code["now"].parent / "avatar.json").read_text())["num_gaussians"]
            for size in sizes:
                times: dict[str, list[float]] = {"before": [], "now": []}
                for _ in range(args.rounds):
                    for code in times:
                        times[code] += time_page(by_code[code], size, args.draws, chromium)
                b, n = statistics.median(times["before"]), statistics.median(times["now"])
                row = {"case": case, "gaussians": gaussians, "size": list(size), "before_ms": b, "now_ms": n}
                rows.append({**row, "times": times})
                print(f"{case}, {size[0]}x{size[1]}: before {b:.1f} ms, now {n:.1f} ms ({b / n:.2f}x)", flush=True)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    print(f"\nmedian time of one draw, waited for (SwiftShader on this CPU; before = {args.before_rev}'s page)\n")
    print("| case | drawing buffer | before | now | speed-up |")
    print("|---|---|---|---|---|")
    for r in rows:
        w, h = r["size"]
        print(
            f"| {r['case']} | {w}x{h} | {r['before_ms']:.1f} ms | {r['now_ms']:.1f} ms | "
            f"{r['before_ms'] / r['now_ms']:.2f}x |"
        )
    out = args.out or results_path("viewer_draw")
    out.write_text(
        json.dumps(
            {
                "machine": {**machine_info(), "webgl": "SwiftShader (software)"},
                "before_rev": args.before_rev,
                "rows": rows,
            },
            indent=1,
        )
    )
    print("saved", out.relative_to(ROOT) if out.is_relative_to(ROOT) else out)


if __name__ == "__main__":
    main()
