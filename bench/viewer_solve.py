"""The webcam mode's per-frame face solve (``solveFace`` in viewer.js) under Node: this checkout's against
the viewer.js of ``--before-rev``, interleaved in one Node process, on the ICT head's landmarks in 4
expressions and poses (640x480, as the webcam tests' synthetic frames) with 0.7 px of Gaussian noise (about
MediaPipe's jitter). Each round solves every frame cold, then times one warm solve from that solution (as
the page solves each camera frame from the last); ``--rounds`` rounds, median of the warm solves. Also
reports the largest difference between the two versions' solved weights.

Usage: python bench/viewer_solve.py [--before-rev HEAD] [--rounds 40] [--out bench/results/viewer_solve-<host>.json]
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from _machine import machine_info, results_path
from viewer import node_or_exit, page_code_at

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT / "tests" / "viewer"), str(ROOT / "tests")]
from test_viewer_webcam import _synthetic_landmarks  # noqa: E402

from meshsplat.track.ict_head import load_ict_head  # noqa: E402
from meshsplat.viewer.webcam import webcam_model  # noqa: E402

JOB = r"""
import fs from "fs";
import { pathToFileURL } from "url";
const [dir, rounds] = [process.argv[2], Number(process.argv[3])];
const versions = { before: await import(pathToFileURL(dir + "/before.mjs").href), now: await import(pathToFileURL(dir + "/now.mjs").href) };
const rd = (n) => new Float32Array(fs.readFileSync(`${dir}/${n}.bin`).buffer.slice(0));
const head = JSON.parse(fs.readFileSync(`${dir}/model.json`, "utf8"));
const lm = new Float64Array(fs.readFileSync(`${dir}/lm.bin`).buffer.slice(0));
const P = 478, T = lm.length / (2 * P), out = {};
for (const [name, M] of Object.entries(versions))
  out[name] = { m: M.decodeWebcam(head, { webcam_neutral: rd("webcam_neutral"), webcam_deltas: rd("webcam_deltas") }), warmMs: [], w: [] };
for (let r = 0; r < rounds; r++) for (const [name, M] of Object.entries(versions)) {
  const o = out[name];
  for (let t = 0; t < T; t++) {
    const obs = lm.subarray(2 * P * t, 2 * P * (t + 1));
    const cold = M.solveFace(o.m, obs, 640, 480, null, {});
    const t0 = performance.now();
    const warm = M.solveFace(o.m, obs, 640, 480, cold, { smooth: 0.1 });
    o.warmMs.push(performance.now() - t0);
    if (r === 0) o.w.push(Array.from(warm.w));
  }
}
console.log(JSON.stringify(Object.fromEntries(Object.entries(out).map(([k, v]) => [k, { warmMs: v.warmMs, w: v.w }]))));
"""


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--before-rev", default="HEAD", help="the commit whose viewer.js is the baseline")
    ap.add_argument("--rounds", type=int, default=40)
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    node = node_or_exit()
    head = load_ict_head()
    sections, header = webcam_model(head)
    lm = _synthetic_landmarks(head)[0].numpy()
    lm = lm + np.random.default_rng(0).normal(0.0, 0.7, lm.shape)
    work = Path(tempfile.mkdtemp(prefix="meshsplat-solve-"))
    try:
        for k, v in sections.items():
            v.astype("<f4").tofile(work / f"{k}.bin")
        (work / "model.json").write_text(json.dumps(header))
        np.ascontiguousarray(lm, "<f8").tofile(work / "lm.bin")
        (work / "before.mjs").write_text(page_code_at(args.before_rev), encoding="utf-8")
        shutil.copy(ROOT / "src/meshsplat/viewer/static/viewer.js", work / "now.mjs")
        (work / "job.mjs").write_text(JOB)
        r = subprocess.run(
            [node, str(work / "job.mjs"), str(work), str(args.rounds)], capture_output=True, text=True, check=True
        )
        res = json.loads(r.stdout)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    diff = float(np.abs(np.asarray(res["before"]["w"]) - np.asarray(res["now"]["w"])).max())
    rows = {
        k: {"warm_ms_median": float(np.median(v["warmMs"])), "warm_ms_p90": float(np.percentile(v["warmMs"], 90))}
        for k, v in res.items()
    }
    for k, v in rows.items():
        print(f"{k:>7}: warm solve {v['warm_ms_median']:.2f} ms median, p90 {v['warm_ms_p90']:.2f}")
    print(f"largest weight difference between the two: {diff:.3g}")
    out = args.out or results_path("viewer_solve")
    doc = {
        "machine": machine_info(),
        "before_rev": args.before_rev,
        "rounds": args.rounds,
        "versions": rows,
        "max_weight_diff": diff,
    }
    out.write_text(json.dumps(doc, indent=1) + "\n")
    print("wrote", out.relative_to(ROOT) if out.is_relative_to(ROOT) else out)


if __name__ == "__main__":
    main()
