"""Benchmark the player's webcam mode (docs/viewer.md, issue 49): frame in -> avatar drawn latency and
solved frames per second in headless Chromium (SwiftShader WebGL2), whose fake camera plays a rendered
ICT head (640x480, 30 frames/s, jawOpen 0.5, smiles 0.6, turned 0.2 rad), and the page's solved
weights against the tracker's offline fit of the same frame (MediaPipe's Python build + ``fit_head``,
identity fixed, no smoothing) and against the rendered truth.

Variants, each in a fresh browser, interleaved over ``--rounds`` rounds so that the shared machine's
load falls on all of them alike:

- ``before``: the page as it was at ``--before-rev`` (its viewer.js, inlined into the same bundle;
  default ca35bdb, the first page that reads the sparse blend-shape rigs today's writer stores; an older
  page needs its own writer, ``--before-src``: 256bbc2, the landmarker on the CPU at 256 px, the avatar
  drawn at the full buffer; 2307bfb: the attention model in WebGL on full camera frames, one landmark pass
  per frame callback);
- ``pipelined``, ``pipelined+cpu``, ``after-plain468``: the current page with the landmarker's options
  set by the URL (``camcpu``, ``camrefine``, ``camsize``) at the full drawing buffer, to tell those apart;
- ``after-nocap``: the current page's draw rules (one draw per solution, re-sorted only when the pose
  moved) at the full drawing buffer with float blending (``campixels=0&camfloat=1``);
- ``after``: the current page with its defaults (+ while its draws are slow, the drawing buffer capped
  and 8-bit blending); ``after-float``: the cap alone (``camfloat=1``); ``after-cap80k``,
  ``after-cap120k``: other caps (``campixels``); ``after-320x240``: the defaults in a 320x240 viewport.

Per run: the page loads, the webcam starts, the first ``--warmup`` solved frames are left out (the
landmarker's first frame takes seconds), then ``--seconds`` are recorded: the page's ``latencyMs``
(``frameIn``, the time the camera frame was noted, to the draw calls that show its solution issued),
``renderedMs`` (to a fence after those draw calls signalled: the pixels rendered; the old page gets the
same fence patched in, its only change), ``landmarkMs``,
``solveMs``, ``drawMs`` (the draw calls issued -> the fence), the drawing buffer's size, solved frames per second (solved frames / wall-clock seconds, in the page's clock) and the
median weights over the window. The load average goes with each run: the machine is shared.

``--avatar RUN``: a trained blend-shape head instead (e.g. a head from ``meshsplat track`` + ``train``), its
page written by ``meshsplat view RUN --animation blendshapes --webcam`` (``before``: the same command with the
old viewer.js; with ``--before-src OTHER/src``, the command of that checkout, its writer and page both, for a
change of the bundle's layout). ``--motion turn``: the camera's head yaws +-0.25 rad once a second (a moving face costs the
landmarker more and re-sorts the avatar).

Usage: python bench/viewer_webcam.py [--rounds 2] [--seconds 15] [--variants before,after]
                                      [--avatar RUN] [--motion still|turn]
                                      [--out bench/results/viewer_webcam-<host>.json]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from _machine import machine_info, results_path
from viewer import meshsplat_with_src, page_code, page_code_at, require_sparse_rigs

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))  # the headless-Chromium driver and fixtures the browser tests use
sys.path.insert(0, str(ROOT / "tests" / "viewer"))
from test_viewer import _small_blendshapes  # noqa: E402
from test_viewer_webcam import serve, write_y4m  # noqa: E402

from _browser import find_chromium, open_page  # noqa: E402
from _eval_kit import make_avatar  # noqa: E402
from meshsplat.track.head_fit import fit_head  # noqa: E402
from meshsplat.track.head_render import render_head  # noqa: E402
from meshsplat.track.ict_head import load_ict_head  # noqa: E402
from meshsplat.track.tracker_camera import focal_from_fov  # noqa: E402
from meshsplat.viewer import write_viewer_bundle  # noqa: E402
from meshsplat.viewer.webcam import find_landmarker, webcam_model  # noqa: E402

W, H, FPS = 640, 480, 30
EXPR = {"jawOpen": 0.5, "mouthSmile_L": 0.6, "mouthSmile_R": 0.6}
ROT = [0.05, 0.2, 0.0]
VARIANTS = {  # name -> (code, URL parameters[, viewport]); the viewport is 640x480 CSS px unless given
    "before": ("before", ""),
    # the landmarker's steps (commit 256bbc2), each at the full drawing buffer (campixels=0)
    # the new frame loop, the old landmarker options
    "pipelined": ("now", "&camcpu=0&camrefine=1&camsize=0&campixels=0"),
    "pipelined+cpu": ("now", "&camcpu=1&camrefine=1&camsize=0&campixels=0"),  # ... with the models on the CPU
    "after-plain468": ("now", "&camrefine=0&campixels=0"),  # ... frames scaled to 256 px, the plain 468-point mesh
    # the avatar's draw while the webcam drives it
    "after-nocap": ("now", "&campixels=0&camfloat=1"),  # one draw per solution, re-sorted when the pose moved
    "after": ("now", ""),  # the defaults: + on slow draws the buffer capped (WEBCAM_PIXELS, 258x193 here), 8-bit
    "after-float": ("now", "&camfloat=1"),  # the cap alone (float blending kept)
    "after-cap80k": ("now", "&campixels=80000"),  # a higher cap (326x244 here), 8-bit
    "after-cap120k": ("now", "&campixels=120000"),  # (400x300 here), 8-bit
    "after-320x240": ("now", "", (320, 240)),  # the defaults in a 320x240 viewport (capped to 258x193 too)
}


OLD_LATENCY = """        cam_.driver.stats.latencyMs.push(performance.now() - cam_.frameIn); cam_.frameIn = null;
"""
FENCED_LATENCY = """        const st = cam_.driver.stats, frameIn = cam_.frameIn, gl = renderer.gl;
        st.latencyMs.push(performance.now() - frameIn); cam_.frameIn = null;
        st.renderedMs = st.renderedMs || [];
        const fence = gl.fenceSync(gl.SYNC_GPU_COMMANDS_COMPLETE, 0);
        gl.flush();
        const poll = () => {
          if (gl.getSyncParameter(fence, gl.SYNC_STATUS) !== gl.SIGNALED) { setTimeout(poll, 1); return; }
          st.renderedMs.push(performance.now() - frameIn); gl.deleteSync(fence);
        };
        setTimeout(poll, 0);
"""


def head_frame(head, rot=ROT) -> np.ndarray:
    """The ICT head in EXPR, turned by ``rot`` (default ROT), 55 cm in front of a 640x480 camera of the page's
    field of view."""
    w = torch.zeros(1, len(head.names))
    for n, x in EXPR.items():
        w[0, head.names.index(n)] = x
    c = (head.neutral.min(0).values + head.neutral.max(0).values) / 2
    v = head.pose(
        torch.zeros_like(head.neutral),
        w,
        torch.zeros(1, 2, 2),
        torch.tensor([list(rot)]),
        (-c + torch.tensor([0, 3.0, -55]))[None],
    )[0]
    f = focal_from_fov(W, H)
    K = torch.tensor([[f, 0, W / 2], [0, f, H / 2], [0, 0, 1.0]])
    return (render_head(head, v, K, W, H)[0].clamp(0, 1).numpy() * 255 + 0.5).astype(np.uint8)


def head_clip(head, motion: str) -> list[np.ndarray]:
    """One second of camera frames: ``still`` (the head in ROT) or ``turn`` (yawing ROT[1] +- 0.25 rad once a
    second, looped by the fake camera)."""
    if motion == "still":
        return [head_frame(head)] * FPS
    return [head_frame(head, (ROT[0], ROT[1] + 0.25 * math.sin(2 * math.pi * i / FPS), ROT[2])) for i in range(FPS)]


def write_bundle(
    out: Path, model, landmarker: Path, viewer_js: str | None, run: Path | None = None, src: Path | None = None
) -> None:
    """The webcam bundle of the browser tests' small avatar, or with ``run`` of that trained head as a user
    makes it (``meshsplat view RUN --animation blendshapes --webcam``); ``viewer_js``: another page's code
    (the baseline); ``src``: write it with another checkout's ``src`` instead (its writer and its page)."""
    if src is not None and run is not None:
        meshsplat_with_src(
            ["view", str(run), "--animation", "blendshapes", "--webcam", str(landmarker), "--out", str(out)], src
        )
        return
    with page_code(viewer_js):
        if run is None:
            av = make_avatar(n=300)
            write_viewer_bundle(av, None, out, rig=_small_blendshapes(av), webcam=model, landmarker=landmarker)
        else:
            from meshsplat.cli.main import main as cli

            argv = ["view", str(run), "--animation", "blendshapes", "--webcam", str(landmarker), "--out", str(out)]
            if cli(argv) != 0:
                raise SystemExit(f"meshsplat {' '.join(argv)} failed")


def run_variant(url: str, clip: Path, chromium: str, warmup: int, seconds: float, viewport=(W, H)) -> dict:
    load0 = os.getloadavg()[0]
    with open_page(url, *viewport, chromium, fake_camera=clip) as page:
        page.wait_ready(120)
        page.evaluate("document.getElementById('webcam').click()")
        get = "(window.meshsplatViewer.webcam || {stats: {frames: 0}}).stats.frames"
        deadline = time.monotonic() + 120
        while page.evaluate(get) < warmup:
            if time.monotonic() > deadline:
                raise RuntimeError(page.evaluate("document.getElementById('camstatus').textContent"))
            time.sleep(0.2)
        start = json.loads(
            page.evaluate(
                "(() => { const s = window.meshsplatViewer.webcam.stats;"
                " for (const k of ['latencyMs', 'renderedMs', 'drawMs', 'landmarkMs', 'solveMs', 'weights']) if (s[k]) s[k].length = 0;"
                " return JSON.stringify({t: performance.now(), frames: s.frames, camera: s.camera || 0,"
                " draws: window.meshsplatViewer.timings.main.length,"
                " dropped: s.dropped || 0, lost: s.lost}); })()"
            )
        )
        time.sleep(seconds)
        end = json.loads(
            page.evaluate(
                "(() => { const s = window.meshsplatViewer.webcam.stats;"
                " const c = document.getElementById('canvas');"
                " return JSON.stringify({...s, t: performance.now(), draws: window.meshsplatViewer.timings.main.length,"
                " buffer: [c.width, c.height]}); })()"
            )
        )
    dt = (end["t"] - start["t"]) / 1000
    lat = np.asarray(end["latencyMs"])
    return {
        "url_query": url.split("?", 1)[1],
        "seconds": round(dt, 2),
        "solved": end["frames"] - start["frames"],
        "solved_fps": round((end["frames"] - start["frames"]) / dt, 2),
        "draws_per_s": round((end["draws"] - start["draws"]) / dt, 2),  # the page's draws (its main-thread timer)
        "drawing_buffer": end["buffer"],
        "camera_fps": round((end.get("camera", 0) - start["camera"]) / dt, 2) if "camera" in end else None,
        "dropped": end.get("dropped", 0) - start["dropped"] if "dropped" in end else None,
        "lost": end["lost"] - start["lost"],
        "latency_ms": {"median": float(np.median(lat)), "p90": float(np.percentile(lat, 90)), "n": len(lat)},
        "rendered_ms": (
            {"median": float(np.median(end["renderedMs"])), "p90": float(np.percentile(end["renderedMs"], 90))}
            if end.get("renderedMs")
            else None
        ),
        "draw_ms": (  # the avatar's draw: its draw calls issued -> its pixels rendered
            {"median": float(np.median(end["drawMs"])), "p90": float(np.percentile(end["drawMs"], 90))}
            if end.get("drawMs")
            else None
        ),
        "landmark_ms": {
            "median": float(np.median(end["landmarkMs"])),
            "p90": float(np.percentile(end["landmarkMs"], 90)),
        },
        "solve_ms": {"median": float(np.median(end["solveMs"])), "p90": float(np.percentile(end["solveMs"], 90))},
        "weights": np.median([s["w"] for s in end["weights"]], axis=0).tolist(),
        "rotation": np.median([s["rot"] for s in end["weights"]], axis=0).tolist(),
        "error_px": float(np.median([s["err"] for s in end["weights"]])),
        "load_avg_1m": [round(load0, 2), round(os.getloadavg()[0], 2)],
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--seconds", type=float, default=15.0)
    ap.add_argument("--warmup", type=int, default=4, help="solved frames left out at the start")
    ap.add_argument("--variants", default=",".join(VARIANTS))
    ap.add_argument(
        "--before-rev", default="ca35bdb", help="the commit whose page is 'before' (older: with --before-src)"
    )
    ap.add_argument(
        "--avatar",
        type=Path,
        default=None,
        help="a trained blend-shape head's run folder (its page as `view --animation blendshapes --webcam` "
        "writes it); default the browser tests' small avatar (300 Gaussians)",
    )
    ap.add_argument("--motion", choices=("still", "turn"), default="still", help="the camera's face: still or turning")
    ap.add_argument(
        "--before-src",
        type=Path,
        default=None,
        help="with --avatar: write the 'before' page with this checkout's src (its writer and page)",
    )
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    chromium = find_chromium()
    if chromium is None:
        sys.exit("chromium is not installed")
    landmarker = find_landmarker(ROOT / ".node-tools")
    head = load_ict_head()
    model = webcam_model(head)
    names = model[1]["names"]
    img = head_frame(head)
    work = Path(tempfile.mkdtemp(prefix="meshsplat-webcam-bench-"))
    clip = write_y4m(work / "face.y4m", head_clip(head, args.motion), fps=FPS)
    old_js = page_code_at(args.before_rev)
    # the one change to an old page without it, for the measurement only: the fence that times its pixels rendered
    if "renderedMs" not in old_js:
        assert OLD_LATENCY in old_js, "the old page's latency timer moved: update OLD_LATENCY"
        old_js = old_js.replace(OLD_LATENCY, FENCED_LATENCY)
    if args.before_src is None or args.avatar is None:  # the page of --before-rev with today's writer
        require_sparse_rigs(old_js, args.before_rev)
    write_bundle(work / "before", model, landmarker, old_js, args.avatar, args.before_src)
    write_bundle(work / "now", model, landmarker, None, args.avatar)
    gaussians = json.loads((work / "now" / "avatar.json").read_text())["num_gaussians"]
    srv, base = serve(work)

    # the tracker's offline fit of the same frame
    from meshsplat.track.mediapipe_models import FaceMesh

    with FaceMesh(max_faces=1, video=False) as fm:
        lm = fm(img)[0]
    fit = fit_head(lm[None].repeat(2, 0), W, H, identity=torch.zeros_like(head.neutral), smoothing=0.0)
    offline = fit.weights[0, head.free_shapes].numpy()
    truth = np.zeros(len(names))
    for n, x in EXPR.items():
        truth[names.index(n)] = x

    runs: list[dict] = []
    try:
        for r in range(args.rounds):
            for name in args.variants.split(","):
                code, query, *viewport = VARIANTS[name]
                viewport = viewport[0] if viewport else (W, H)
                res = run_variant(
                    f"{base}/{code}/index.html?play=0{query}", clip, chromium, args.warmup, args.seconds, viewport
                )
                res["viewport"] = list(viewport)
                w = np.asarray(res.pop("weights"))
                res.update(
                    variant=name,
                    round=r,
                    vs_offline={"mean": float(np.abs(w - offline).mean()), "max": float(np.abs(w - offline).max())},
                    vs_offline_expr={n: round(float(w[names.index(n)] - offline[names.index(n)]), 3) for n in EXPR},
                    vs_truth_expr={n: round(float(w[names.index(n)] - truth[names.index(n)]), 3) for n in EXPR},
                )
                runs.append(res)
                print(
                    f"{name:13s} r{r}: latency {res['latency_ms']['median']:.0f}/{res['latency_ms']['p90']:.0f} ms "
                    f"(median/p90; rendered {res['rendered_ms']}), {res['solved_fps']:.1f} solved/s (camera {res['camera_fps']}), landmarks "
                    f"{res['landmark_ms']['median']:.0f} ms, solve {res['solve_ms']['median']:.1f} ms, |w - offline| "
                    f"mean {res['vs_offline']['mean']:.3f} max {res['vs_offline']['max']:.3f}, expr-offline "
                    f"{res['vs_offline_expr']}, load {res['load_avg_1m']}",
                    flush=True,
                )
    finally:
        srv.shutdown()
        shutil.rmtree(work, ignore_errors=True)
    out = args.out or results_path("viewer_webcam")
    out.write_text(
        json.dumps(
            {
                "machine": {
                    **machine_info(),
                    "webgl": "SwiftShader (software)",
                    "chromium": chromium.rsplit("/", 1)[-1],
                },
                "clip": {
                    "width": W,
                    "height": H,
                    "fps": FPS,
                    "expression": EXPR,
                    "rotation": ROT,
                    "motion": args.motion,
                },
                "avatar": {
                    "run": args.avatar.name if args.avatar else "the browser tests' small avatar",
                    "gaussians": gaussians,
                },
                "before_rev": args.before_rev,
                "before_src": bool(args.before_src),
                "offline_expr": {n: round(float(offline[names.index(n)]), 3) for n in EXPR},
                "runs": runs,
            },
            indent=1,
        )
    )
    print("wrote", out.relative_to(ROOT) if out.is_relative_to(ROOT) else out)


if __name__ == "__main__":
    main()
