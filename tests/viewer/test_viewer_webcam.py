"""The player's webcam mode (docs/viewer.md): the landmark model in the bundle, the page's per-frame
face solve (``solveFace``, Node) against the tracker's offline fit (``fit_head``) and the ground truth,
and (slow, Chromium with a fake camera playing a rendered ICT head) the whole loop: camera -> MediaPipe
landmarks in the page -> solve -> the avatar's morph weights."""

from __future__ import annotations

import functools
import http.server
import json
import math
import os
import shutil
import subprocess
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from test_viewer import _chromium, _small_blendshapes

from _browser import open_page
from _eval_kit import make_avatar
from meshsplat.errors import MeshsplatError
from meshsplat.track.head_fit import fit_head
from meshsplat.track.ict_head import load_ict_head
from meshsplat.track.tracker_camera import focal_from_fov, project
from meshsplat.viewer import read_viewer_bundle, write_viewer_bundle
from meshsplat.viewer.webcam import LANDMARKER_FILES, LANDMARKER_VERSION, find_landmarker, webcam_model

NODE = shutil.which("node")
VIEWER_JS = Path(__file__).resolve().parents[2] / "src/meshsplat/viewer/static/viewer.js"
needs_node = pytest.mark.skipif(NODE is None, reason="node is not installed")


@pytest.fixture(scope="module")
def head():
    return load_ict_head()


@pytest.fixture(scope="module")
def model(head):
    return webcam_model(head)


def _fake_landmarker(folder: Path) -> Path:
    folder.mkdir(parents=True)
    for f in LANDMARKER_FILES:
        (folder / f).write_text("x")
    return folder


def _installed_landmarker() -> Path:
    try:
        return find_landmarker()
    except MeshsplatError:
        pass
    if os.environ.get("MESHSPLAT_REQUIRE_BROWSER") == "1":
        pytest.fail("@mediapipe/face_mesh is not installed (make node-tools)")
    pytest.skip("@mediapipe/face_mesh is not installed (make node-tools)")


def test_landmarker_version_is_the_makefiles():
    """`make node-tools` installs the release the page is written for (0.4.1657299874 cannot start its detector)."""
    text = (Path(__file__).resolve().parents[2] / "Makefile").read_text()
    assert text.split("@mediapipe/face_mesh@", 1)[1].split()[0] == LANDMARKER_VERSION


def test_webcam_model_is_the_landmark_basis(head, model):
    sections, header = model
    free = head.free_shapes
    assert header["names"] == [head.names[i] for i in free] and len(free) == 47
    assert sections["webcam_neutral"].shape == (478, 3) and sections["webcam_deltas"].shape == (47, 478, 3)
    # the basis reproduces the head's landmarks for any weights (no gaze, no pose)
    w = torch.zeros(1, len(head.names))
    w[0, free] = torch.rand(len(free), generator=torch.Generator().manual_seed(0))
    v = head.pose(torch.zeros_like(head.neutral), w, torch.zeros(1, 2, 2), torch.zeros(1, 3), torch.zeros(1, 3))[0]
    mine = sections["webcam_neutral"] + np.einsum("e,elc->lc", w[0, free].numpy(), sections["webcam_deltas"])
    np.testing.assert_allclose(mine, head.landmarks(v).numpy(), atol=1e-4)
    assert len(header["used"]) == 468  # the 10 iris points (gaze) are left out


def test_bundle_with_webcam(tmp_path, model):
    av = make_avatar(n=40)
    drv = _small_blendshapes(av)  # jawOpen, mouthSmile_L, browInnerUp_L, eyeBlink_R
    lm = _fake_landmarker(tmp_path / "pkg" / "node_modules" / "@mediapipe" / "face_mesh")
    write_viewer_bundle(av, None, tmp_path / "v", rig=drv, webcam=model, landmarker=tmp_path / "pkg")
    h, a = read_viewer_bundle(tmp_path / "v")
    names = h["webcam"]["names"]
    assert h["webcam"]["targets"][names.index("jawOpen")] == 0
    assert h["webcam"]["targets"][names.index("eyeBlink_R")] == 3
    assert sum(t >= 0 for t in h["webcam"]["targets"]) == 4
    assert a["webcam_deltas"].shape == (47, 478, 3)
    copied = sorted(p.name for p in (tmp_path / "v" / "face_mesh").iterdir())
    assert copied == sorted([*LANDMARKER_FILES, "LICENSE", "NOTICE"])
    assert "Apache License" in (tmp_path / "v" / "face_mesh" / "LICENSE").read_text()
    assert lm.is_dir()
    # no landmarker: one line naming the npm package and how to install it
    with pytest.raises(MeshsplatError, match=f"npm install .*@mediapipe/face_mesh@{LANDMARKER_VERSION}"):
        write_viewer_bundle(av, None, tmp_path / "w", rig=drv, webcam=model, landmarker=tmp_path / "nowhere")
    # vertex frames, or a rig without ARKit names: refused
    with pytest.raises(MeshsplatError, match="live blend-shape head"):
        write_viewer_bundle(av, [av.mesh.vertices], tmp_path / "x", webcam=model, landmarker=tmp_path / "pkg")
    drv.names = ["a", "b", "c", "d"]
    with pytest.raises(MeshsplatError, match="none of the ARKit names"):
        write_viewer_bundle(av, None, tmp_path / "y", rig=drv, webcam=model, landmarker=tmp_path / "pkg")


def _synthetic_landmarks(head):
    """Landmarks of the ICT head (no gaze) in 4 expressions and poses, projected at 640x480."""
    W, H = 640, 480
    f = focal_from_fov(W, H)
    K = torch.tensor([[f, 0, W / 2], [0, f, H / 2], [0, 0, 1.0]])
    T = 4
    w = torch.zeros(T, len(head.names))
    for name, vals in {
        "jawOpen": [0.0, 0.4, 0.7, 0.2],
        "mouthSmile_L": [0, 0.5, 0.2, 0.6],
        "mouthSmile_R": [0, 0.5, 0.1, 0.6],
        "eyeBlink_L": [0, 0.8, 0, 0.3],
        "browInnerUp_L": [0, 0.3, 0.6, 0],
        "browInnerUp_R": [0, 0.3, 0.6, 0],
    }.items():
        w[:, head.names.index(name)] = torch.tensor(vals)
    rot = torch.tensor([[0, 0, 0], [0.1, -0.25, 0.05], [-0.15, 0.3, 0.0], [0.05, 0.1, -0.1]])
    c = (head.neutral.min(0).values + head.neutral.max(0).values) / 2
    trans = -c + torch.tensor([0.0, 3.0, -55.0]) + torch.tensor([[0, 0, 0], [2, -1, 3], [-3, 1, -4], [1, 2, 0.0]])
    v = head.pose(torch.zeros_like(head.neutral), w, torch.zeros(T, 2, 2), rot, trans)
    return project(head.landmarks(v), K), w, rot, W, H


def _js_solve(tmp_path: Path, model, landmarks: np.ndarray, W: int, H: int, chain: bool = False) -> list[dict]:
    """``landmarks`` [T, P, 2]: P = 478, or 468 (the plain mesh's, no iris points)."""
    sections, header = model
    for k, v in sections.items():
        v.astype("<f4").tofile(tmp_path / f"{k}.bin")
    (tmp_path / "model.json").write_text(json.dumps(header))
    np.ascontiguousarray(landmarks, "<f8").tofile(tmp_path / "lm.bin")
    script = f"""
import {{ decodeWebcam, solveFace }} from {json.dumps(VIEWER_JS.as_uri())};
import fs from "fs";
const dir = {json.dumps(str(tmp_path))};
const rd = (n) => new Float32Array(fs.readFileSync(`${{dir}}/${{n}}.bin`).buffer.slice(0));
const m = decodeWebcam(JSON.parse(fs.readFileSync(`${{dir}}/model.json`)),
                       {{ webcam_neutral: rd("webcam_neutral"), webcam_deltas: rd("webcam_deltas") }});
const lm = new Float64Array(fs.readFileSync(`${{dir}}/lm.bin`).buffer.slice(0));
const P = {landmarks.shape[1]}, T = lm.length / (2 * P), out = [];
let prev = null;
for (let t = 0; t < T; t++) {{
  const obs = lm.subarray(2 * P * t, 2 * P * (t + 1));
  const t0 = performance.now();
  const s = solveFace(m, obs, {W}, {H}, {"prev" if chain else "null"}, {{}});
  const cold = performance.now() - t0;
  const t1 = performance.now();
  solveFace(m, obs, {W}, {H}, s, {{ smooth: 0.1 }}); // a warm frame, as the page's
  out.push({{ w: Array.from(s.w), rot: s.rot, err: s.errorPx, ms: cold, warmMs: performance.now() - t1 }});
  prev = s;
}}
console.log(JSON.stringify(out));
"""
    (tmp_path / "solve.mjs").write_text(script)
    r = subprocess.run([NODE, str(tmp_path / "solve.mjs")], capture_output=True, text=True, timeout=120, check=False)
    assert r.returncode == 0, r.stderr
    return json.loads(r.stdout)


@needs_node
def test_js_face_solve_matches_truth_and_head_fit(tmp_path, head, model):
    """On exact landmarks the page's solve finds the weights and pose (the landmarks determine them);
    the tracker's offline fit (Adam, identity fixed, no smoothing) lands near them too."""
    lm, w, rot, W, H = _synthetic_landmarks(head)
    js = _js_solve(tmp_path, model, lm.numpy(), W, H)
    free = head.free_shapes
    fit = fit_head(lm, W, H, identity=torch.zeros_like(head.neutral), smoothing=0.0)
    for t, s in enumerate(js):
        jw, truth, offline = np.asarray(s["w"]), w[t, free].numpy(), fit.weights[t, free].numpy()
        assert np.abs(jw - truth).max() < 0.01, (t, np.abs(jw - truth).max())
        np.testing.assert_allclose(s["rot"], rot[t].numpy(), atol=2e-3)
        assert s["err"] < 0.05  # pixels
        # the offline fit: within 0.15 of both (measured 0.03-0.13: its L1 prior and Adam's stopping point)
        assert np.abs(jw - offline).max() < 0.15, (t, np.abs(jw - offline).max())
        np.testing.assert_allclose(s["rot"], fit.rotations[t].numpy(), atol=0.01)
    print("solve ms (cold, warm):", [(round(s["ms"], 1), round(s["warmMs"], 1)) for s in js])


@needs_node
def test_js_face_solve_on_the_plain_mesh(tmp_path, head, model):
    """MediaPipe's plain face mesh gives 468 points (no iris): the solve uses none beyond them
    (``used`` is 0..467) and finds the same weights and pose."""
    assert model[1]["used"] == list(range(468))
    lm, w, rot, W, H = _synthetic_landmarks(head)
    js = _js_solve(tmp_path, model, lm.numpy()[:, :468], W, H)
    for t, s in enumerate(js):
        assert np.abs(np.asarray(s["w"]) - w[t, head.free_shapes].numpy()).max() < 0.01, t
        np.testing.assert_allclose(s["rot"], rot[t].numpy(), atol=2e-3)
        assert s["err"] < 0.05


@needs_node
def test_webcam_driver_moves_the_head(tmp_path, head, model):
    """The driver passes the head's move since the first solved frame (cm; x mirrored by default; smoothed as
    the rotation) on with each pose; "neutral" makes the current place the rest."""
    W, H = 640, 480
    f = focal_from_fov(W, H)
    K = torch.tensor([[f, 0, W / 2], [0, f, H / 2], [0, 0, 1.0]])
    c = (head.neutral.min(0).values + head.neutral.max(0).values) / 2
    moves = torch.tensor([[0, 0, 0], [2.0, -1.0, 3.0], [2.0, -1.0, 3.0]])
    z = torch.zeros(3, len(head.names))
    v = head.pose(
        torch.zeros_like(head.neutral),
        z,
        torch.zeros(3, 2, 2),
        torch.zeros(3, 3),
        -c + torch.tensor([0, 3.0, -55]) + moves,
    )
    lm = project(head.landmarks(v), K).numpy()  # [3, 478, 2] pixels
    sections, header = model
    for k, a in sections.items():
        a.astype("<f4").tofile(tmp_path / f"{k}.bin")
    (tmp_path / "model.json").write_text(json.dumps(header))
    (tmp_path / "lm.json").write_text(json.dumps((lm / [W, H]).tolist()))
    script = f"""
import {{ decodeWebcam, WebcamDriver }} from {json.dumps(VIEWER_JS.as_uri())};
import fs from "fs";
const dir = {json.dumps(str(tmp_path))};
const rd = (n) => new Float32Array(fs.readFileSync(`${{dir}}/${{n}}.bin`).buffer.slice(0));
const m = decodeWebcam(JSON.parse(fs.readFileSync(`${{dir}}/model.json`)),
                       {{ webcam_neutral: rd("webcam_neutral"), webcam_deltas: rd("webcam_deltas") }});
const frames = JSON.parse(fs.readFileSync(`${{dir}}/lm.json`));
const out = [];
const d = new WebcamDriver({{}}, {{ webcam: m }}, (w, q, t, move) => out.push({{ move, t: d.prev.t }}), () => {{}});
d.running = true; d.frameW = {W}; d.frameH = {H}; d.stats.latencyMs = [];
for (const fr of frames) d.results({{ multiFaceLandmarks: [fr.map(([x, y]) => ({{ x, y }}))] }});
d.calibrate();
d.results({{ multiFaceLandmarks: [frames[2].map(([x, y]) => ({{ x, y }}))] }});
console.log(JSON.stringify(out));
"""
    (tmp_path / "t.mjs").write_text(script)
    r = subprocess.run([NODE, str(tmp_path / "t.mjs")], capture_output=True, text=True, timeout=120, check=False)
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    assert out[0]["move"] == [0, 0, 0]
    solved = np.subtract(out[1]["t"], out[0]["t"])  # the solve's own move: the rendered one, nearly
    np.testing.assert_allclose(solved, moves[1].numpy(), atol=0.3)
    mirror = np.array([-1, 1, 1])
    np.testing.assert_allclose(out[1]["move"], 0.6 * mirror * solved, atol=1e-9)  # smoothed (0.6) and mirrored
    np.testing.assert_allclose(
        out[2]["move"],
        out[1]["move"] + 0.6 * (mirror * np.subtract(out[2]["t"], out[0]["t"]) - out[1]["move"]),
        atol=1e-9,
    )
    assert np.abs(out[3]["move"]).max() < 1e-3  # after "neutral": the current place is the rest (the same frame again)


@needs_node
def test_webcam_drawing_buffer_cap(tmp_path):
    """The drawing buffer's size rule (drawingSize): without a cap (webcam off) the page's rule as before
    (the screen's pixel ratio, capped by the quality setting and 4 MP); with one (webcam mode) at most that
    many pixels, the aspect kept, never larger than without; and the webcam's re-sort tolerance."""
    script = f"""
import {{ drawingSize, webcamPoseClose, WEBCAM_PIXELS, WEBCAM_RESORT }} from {json.dumps(VIEWER_JS.as_uri())};
const old = (cw, ch, ratio, quality, budget) => {{  // the rule before webcam mode's cap
  let dpr = Math.min(ratio || 1, quality || 2);
  const css = Math.max(cw * ch, 1);
  if (css * dpr * dpr > budget) dpr = Math.max(1, Math.sqrt(budget / css));
  return [Math.round(cw * dpr), Math.round(ch * dpr)];
}};
const out = {{ cases: [], WEBCAM_PIXELS, WEBCAM_RESORT }};
for (const [cw, ch, r, q] of [[640, 480, 1, 2], [320, 240, 1, 2], [390, 844, 3, 2], [1920, 1080, 2, 2], [1280, 720, 1.5, 1], [200, 100, 1, 2]]) {{
  out.cases.push({{ args: [cw, ch, r, q], old: old(cw, ch, r, q, 4e6), off: drawingSize(cw, ch, r, q, 4e6, 0),
                   on: drawingSize(cw, ch, r, q, 4e6, WEBCAM_PIXELS) }});
}}
const pose = (w, angle, t) => ({{ weights: [w, 0], rotation: {{ rotation: [0, Math.sin(angle / 2), 0, Math.cos(angle / 2)], translation: [t, 0, 0] }} }});
const a = pose(0.5, 0.1, 0);
out.close = [webcamPoseClose(a, pose(0.53, 0.11, 0.005), 1), webcamPoseClose(a, pose(0.6, 0.1, 0), 1),
             webcamPoseClose(a, pose(0.5, 0.13, 0), 1), webcamPoseClose(a, pose(0.5, 0.1, 0.02), 1), webcamPoseClose(null, a, 1)];
console.log(JSON.stringify(out));
"""
    (tmp_path / "t.mjs").write_text(script)
    r = subprocess.run([NODE, str(tmp_path / "t.mjs")], capture_output=True, text=True, timeout=60, check=False)
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    cap = out["WEBCAM_PIXELS"]
    assert 20000 <= cap <= 150000
    for c in out["cases"]:
        off, on = c["off"], c["on"]
        assert [off["w"], off["h"]] == c["old"] == [off["fullW"], off["fullH"]], c  # webcam off: as before
        assert [on["fullW"], on["fullH"]] == c["old"], c  # the view readout's size does not change
        assert on["w"] * on["h"] <= max(cap, off["w"] * off["h"]) and on["w"] <= off["w"] and on["h"] <= off["h"], c
        if off["w"] * off["h"] > cap:
            assert on["w"] * on["h"] > 0.95 * cap, c  # the cap used, not much less
            assert on["w"] / on["h"] == pytest.approx(off["w"] / off["h"], rel=0.02), c
        else:
            assert [on["w"], on["h"]] == [off["w"], off["h"]], c
    assert out["close"] == [True, False, False, False, False]


def _head_image(head, weights: dict[str, float], rot, size: int = 256) -> np.ndarray:
    from meshsplat.track.head_render import render_head

    w = torch.zeros(1, len(head.names))
    for n, x in weights.items():
        w[0, head.names.index(n)] = x
    c = (head.neutral.min(0).values + head.neutral.max(0).values) / 2
    v = head.pose(
        torch.zeros_like(head.neutral),
        w,
        torch.zeros(1, 2, 2),
        torch.tensor([rot]),
        (-c + torch.tensor([0, 3.0, -55]))[None],
    )[0]
    f = size / (2 * math.tan(math.radians(20)))
    K = torch.tensor([[f, 0, size / 2], [0, f, size / 2], [0, 0, 1.0]])
    return (render_head(head, v, K, size, size)[0].clamp(0, 1).numpy() * 255 + 0.5).astype(np.uint8)


def write_y4m(path: Path, frames: list[np.ndarray], fps: int = 10) -> Path:
    """RGB uint8 frames (even sizes) -> a YUV4MPEG2 4:2:0 file (Chromium's fake camera plays it in a loop)."""
    h, w = frames[0].shape[:2]
    with open(path, "wb") as f:
        f.write(f"YUV4MPEG2 W{w} H{h} F{fps}:1 Ip A1:1 C420jpeg\n".encode())
        for fr in frames:
            r, g, b = (fr[..., i].astype(np.float64) for i in range(3))
            y = 0.299 * r + 0.587 * g + 0.114 * b
            u = 128 - 0.168736 * r - 0.331264 * g + 0.5 * b
            v = 128 + 0.5 * r - 0.418688 * g - 0.081312 * b
            f.write(b"FRAME\n")
            for plane in (
                y,
                u.reshape(h // 2, 2, w // 2, 2).mean((1, 3)),
                v.reshape(h // 2, 2, w // 2, 2).mean((1, 3)),
            ):
                f.write(np.clip(np.rint(plane), 0, 255).astype(np.uint8).tobytes())
    return path


class _Quiet(http.server.SimpleHTTPRequestHandler):
    def log_message(self, *args):
        pass


def serve(folder: Path):
    """A loopback HTTP server of ``folder`` (the webcam mode needs an http page): (server, base url)."""
    srv = http.server.ThreadingHTTPServer(("127.0.0.1", 0), functools.partial(_Quiet, directory=str(folder)))
    threading.Thread(target=srv.serve_forever, daemon=True).start()
    return srv, f"http://127.0.0.1:{srv.server_address[1]}"


@pytest.mark.slow
def test_browser_webcam_drives_the_head(tmp_path, head, model):
    """A fake camera plays a rendered ICT head (jaw open, smiling, turned): the page finds its landmarks,
    solves, and drives the avatar's morph targets; the page's weights agree with the tracker's offline fit
    of the same image (MediaPipe in Python + fit_head) and with the rendered truth."""
    chromium = _chromium()
    landmarker = _installed_landmarker()
    expr = {"jawOpen": 0.5, "mouthSmile_L": 0.6, "mouthSmile_R": 0.6}
    img = _head_image(head, expr, [0.05, 0.2, 0.0])
    clip = write_y4m(tmp_path / "face.y4m", [img, img])
    av = make_avatar(n=300)
    drv = _small_blendshapes(av)
    write_viewer_bundle(av, None, tmp_path / "v", rig=drv, webcam=model, landmarker=landmarker)
    srv, base = serve(tmp_path / "v")
    try:
        with open_page(f"{base}/index.html?play=0", 640, 480, chromium, fake_camera=clip) as page:
            page.wait_ready(60)
            size_js = "(() => { const c = document.getElementById('canvas'); return [c.width, c.height]; })()"
            size_off = page.evaluate(size_js)
            page.evaluate("document.getElementById('webcam').click()")
            deadline = time.monotonic() + 60
            while time.monotonic() < deadline:
                n = page.evaluate("(window.meshsplatViewer.webcam || {stats: {frames: 0}}).stats.frames")
                if n >= 6:
                    break
                time.sleep(0.25)
            stats = page.evaluate("JSON.stringify(window.meshsplatViewer.webcam.stats)")
            shown = page.evaluate("Array.from(window.meshsplatViewer.webcam.smoothW)")
            node_rot = page.evaluate("Array.from(window.meshsplatViewer.webcam.lastRotation)")
            move = page.evaluate("Array.from(window.meshsplatViewer.webcam.lastTranslation)")
            page.screenshot(tmp_path / "webcam.png")
            status = page.evaluate("document.getElementById('camstatus').textContent")
            size_on, view_on = page.evaluate(size_js), page.evaluate("window.meshsplatViewer.viewString")
            page.evaluate("document.getElementById('camstop').click()")
            time.sleep(1.0)
            size_stopped = page.evaluate(size_js)
    finally:
        srv.shutdown()
    st = json.loads(stats)
    assert st["frames"] >= 6, status
    # the drawing buffer: the page's own size with the webcam off and after "stop"; while the webcam drives
    # the avatar and its draws are slow (software WebGL here), capped at WEBCAM_PIXELS (and the CSS size kept)
    assert size_off == [640, 480] and size_stopped == [640, 480], (size_off, size_stopped)
    if np.median(st["drawMs"][:5]) > 20:
        assert size_on[0] * size_on[1] <= 50000 and size_on[0] / size_on[1] == pytest.approx(4 / 3, abs=0.02), size_on
    else:
        assert size_on == [640, 480], (size_on, st["drawMs"])
    assert view_on.endswith(",640,480"), view_on  # the view readout names the page's size, capped or not
    names = model[1]["names"]
    page_w = np.median([s["w"] for s in st["weights"][2:]], axis=0)  # after the tracker settles
    smile_l_raw = st["weights"][-1]["w"][names.index("mouthSmile_L")]
    assert np.median([s["err"] for s in st["weights"]]) < 3.0  # pixels of a 256² frame
    # the head's turn (0.05, 0.2, 0 rad as rendered) reaches the avatar's head node
    np.testing.assert_allclose(np.median([s["rot"] for s in st["weights"][2:]], axis=0), [0.05, 0.2, 0.0], atol=0.06)
    # mirrored (the default): the rig's rotation (quaternion xyzw) turns the other way about y, ~0.2 rad
    assert abs(node_rot[1] + math.sin(0.1)) < 0.05 and abs(node_rot[0] - math.sin(0.025)) < 0.05
    # a still face: the head stays about where it was first seen (cm; measured 0.16-0.19 across, 0.5 in depth,
    # which the warm frames settle differently from the first, cold one)
    assert np.abs(move).max() < 1.0, move
    assert model[1]["head_size_cm"] > 10
    # the offline fit of the same frame (MediaPipe's Python build, the tracker's solver)
    from meshsplat.track.mediapipe_models import FaceMesh

    with FaceMesh(max_faces=1, video=False) as fm:
        lm = fm(img)[0]
    fit = fit_head(lm[None].repeat(2, 0), 256, 256, identity=torch.zeros_like(head.neutral), smoothing=0.0)
    offline = fit.weights[0, head.free_shapes].numpy()
    for n in expr:
        i = names.index(n)
        assert abs(page_w[i] - offline[i]) < 0.2, (n, page_w[i], offline[i])
        assert abs(page_w[i] - expr[n]) < 0.3, (n, page_w[i])
    lat, lmk, solve = (np.median(st[k]) for k in ("latencyMs", "landmarkMs", "solveMs"))
    settled = st["weights"][2:]  # after the landmarker's first (warm-up) frames
    fps = (len(settled) - 1) / max((settled[-1]["t"] - settled[0]["t"]) / 1000, 1e-3)
    print(
        f"webcam (software WebGL): landmarks {lmk:.0f} ms, solve {solve:.1f} ms, frame in -> drawn {lat:.0f} ms, "
        f"{fps:.1f} solved frames/s; |page - offline| mean {np.abs(page_w - offline).mean():.3f} "
        f"max {np.abs(page_w - offline).max():.3f}"
    )
    # over all 47 shapes the two solvers of a real (noisy, other identity) face differ more than on exact
    # landmarks: the shapes the image barely tells apart (brows, cheeks) trade places
    assert np.abs(page_w - offline).mean() < 0.15
    assert shown[names.index("jawOpen")] > 0.25  # what the avatar shows
    # ... with the sides swapped (mirrored): the avatar's mouthSmile_R is the face's mouthSmile_L
    assert shown[names.index("mouthSmile_R")] == pytest.approx(smile_l_raw, abs=0.15)


@pytest.mark.slow
def test_browser_webcam_rebuilds_shadows_at_most_every_250_ms(tmp_path, head, model):
    """A key-lit head driven by a turning face: the shadow worker rebuilds the height maps at most every
    WEBCAM_SHADOW_MS while the webcam drives the avatar (whose tiny mesh would let it rebuild for every
    solution), and the shown pose still gets its maps."""
    from test_viewer import key_shading

    from meshsplat.gaussians import Avatar

    chromium = _chromium()
    landmarker = _installed_landmarker()
    frames = [_head_image(head, {"jawOpen": 0.3}, [0.05, 0.25 * math.sin(2 * math.pi * i / 8), 0.0]) for i in range(8)]
    clip = write_y4m(tmp_path / "face.y4m", frames, fps=20)
    base_av = make_avatar(n=300)
    av = Avatar(base_av.mesh, base_av.params, base_av.scale_mode, shading=key_shading((0.6, 0.3, 0.75), grid=32))
    write_viewer_bundle(av, None, tmp_path / "v", rig=_small_blendshapes(av), webcam=model, landmarker=landmarker)
    srv, base = serve(tmp_path / "v")
    count = "window.meshsplatViewer.timings.key.length"
    try:
        with open_page(f"{base}/index.html?play=0", 640, 480, chromium, fake_camera=clip) as page:
            page.wait_ready(60)
            page.evaluate("document.getElementById('webcam').click()")
            deadline = time.monotonic() + 60
            while page.evaluate("(window.meshsplatViewer.webcam || {stats: {frames: 0}}).stats.frames") < 3:
                assert time.monotonic() < deadline, page.evaluate("document.getElementById('camstatus').textContent")
                time.sleep(0.1)
            built0, frames0, t0 = (
                page.evaluate(count),
                page.evaluate("window.meshsplatViewer.webcam.stats.frames"),
                time.monotonic(),
            )
            time.sleep(3.0)
            built, solved, dt = (
                page.evaluate(count) - built0,
                page.evaluate("window.meshsplatViewer.webcam.stats.frames") - frames0,
                time.monotonic() - t0,
            )
            page.evaluate("document.getElementById('camstop').click()")
            time.sleep(0.5)
            state = json.loads(page.evaluate("JSON.stringify(window.meshsplatViewer.state)"))
    finally:
        srv.shutdown()
    print(f"webcam with a key light: {solved} solutions, {built} height-map builds in {dt:.1f} s")
    assert solved >= 10, solved  # the face moved: every solution is a new pose
    assert 1 <= built <= dt / 0.25 + 2, (built, dt)
    assert built < solved
    assert state["shadowKey"] == state["poseKey"]  # after "stop" the shown pose has its own maps


def test_view_cli_webcam_needs_a_live_head(tmp_path, capsys):
    """`meshsplat view --webcam` on vertex frames says what it needs, in one line."""
    from _eval_kit import make_run
    from meshsplat.cli.main import main

    av = make_avatar(n=40)
    run = make_run(av, tmp_path / "run", None)
    np.save(tmp_path / "seq.npy", torch.stack([av.mesh.vertices, av.mesh.vertices]).numpy())
    argv = ["view", str(run), "--out", str(tmp_path / "v"), "--animation", "vertices", str(tmp_path / "seq.npy")]
    assert main([*argv, "--webcam"]) == 2
    assert "--webcam: needs a live blend-shape head" in capsys.readouterr().err


@needs_node
def test_camera_refusals_are_explained(tmp_path):
    """What the page says when the camera is refused, absent or busy (getUserMedia's errors), and on file://."""
    script = f"""
import {{ cameraErrorText, WebcamDriver }} from {json.dumps(VIEWER_JS.as_uri())};
const out = ["NotAllowedError", "NotFoundError", "NotReadableError", "TypeError"].map((name) => cameraErrorText({{ name }}));
const doc = {{ location: {{ protocol: "file:" }}, defaultView: {{ navigator: {{}} }} }};
try {{ await new WebcamDriver(doc, {{}}, null, () => {{}}).start(null); }} catch (err) {{ out.push(err.message); }}
doc.location.protocol = "http:";
try {{ await new WebcamDriver(doc, {{}}, null, () => {{}}).start(null); }} catch (err) {{ out.push(err.message); }}
console.log(JSON.stringify(out));
"""
    (tmp_path / "t.mjs").write_text(script)
    r = subprocess.run([NODE, str(tmp_path / "t.mjs")], capture_output=True, text=True, timeout=60, check=False)
    assert r.returncode == 0, r.stderr
    refused, absent, busy, other, on_file, no_media = json.loads(r.stdout)
    assert "refused" in refused and "allow the camera" in refused
    assert "no camera found" in absent and "busy" in busy and "TypeError" in other
    assert "served over http" in on_file and "--serve" in on_file
    assert "gives no camera" in no_media
