"""The web player's CPU work per pose for a trained blend-shape head, under Node: the rig skinned on the
CPU (``skinVertices``), the sort worker's job (``sortJob``: skinning, vertex normals, depth keys, sort) and
the shadow worker's job (``shadowJob``: skinning, the key light's height maps), and the page's size; this
checkout's page against ``--before-src``'s (another checkout's ``src``: its bundle writer and its page), each
page written by ``meshsplat view RUN --animation blendshapes``.

Each call poses the head with new weights (all 57 at 0.3, one swept); the two pages alternate call by
call (``--calls`` each after 3 warm-up calls), so the shared machine's load falls on both alike; medians
of CPU-bound wall time (one Node thread each).

Usage: python bench/viewer_workers.py RUN --before-src OTHER/src [--calls 15]
                                      [--out bench/results/viewer_workers-<host>.json]
"""

from __future__ import annotations

import argparse
import json
import shutil
import statistics
import subprocess
import tempfile
from pathlib import Path

from _machine import machine_info, results_path
from viewer import meshsplat_with_src, node_or_exit

ROOT = Path(__file__).resolve().parents[1]

NODE_JOB = r"""
import fs from "fs";
import { pathToFileURL } from "url";
const pages = JSON.parse(process.argv[2]), calls = Number(process.argv[3]);
const mods = {}, states = {};
for (const [name, dir] of Object.entries(pages)) {
  const m = mods[name] = await import(pathToFileURL(dir + "/viewer.js").href);
  const b = m.decodeBundle(JSON.parse(fs.readFileSync(dir + "/avatar.json", "utf8")), fs.readFileSync(dir + "/avatar.bin"));
  const shadow = b.header.shading && b.header.shading.key ? Object.assign(m.shadowSetup(b), { spare: [] }) : null;
  states[name] = { b, poser: new m.FramePoser(b), sort: m.sortScratch(m.sortSetup(b)), shadow,
                   viewmat: m.orbitViewmat([0, 0, 0], 60, 10, 5) };
}
const out = {};
for (const name of Object.keys(pages)) out[name] = { skin: [], sort: [], shadow: [] };
for (let c = 0; c < calls + 3; c++) {
  for (const [name, m] of Object.entries(mods)) {
    const s = states[name], w = new Float64Array(s.b.rig.defaultWeights.length).fill(0.3);
    w[c % w.length] = 0.3 + 0.05 * (c % 7);
    const pose = s.poser.rig(null, 0, w, undefined);
    const rig = { pairs: pose.rig.pairs.slice(), weights: pose.rig.weights.slice() };
    let t = performance.now();
    m.skinVertices(s.b.rig, rig, s.b.V);
    const skin = performance.now() - t;
    t = performance.now();
    m.sortJob(s.sort, { rig, viewmat: s.viewmat });
    const sort = performance.now() - t;
    let shadow = null;
    if (s.shadow) { t = performance.now(); const r = m.shadowJob(s.shadow, { rig }); shadow = performance.now() - t; s.shadow.spare.push(r.depth); }
    if (c >= 3) { out[name].skin.push(skin); out[name].sort.push(sort); if (shadow !== null) out[name].shadow.push(shadow); }
  }
}
console.log(JSON.stringify(out));
"""


def write_page(run: Path, out: Path, src: Path | None) -> dict:
    meshsplat_with_src(["view", str(run), "--animation", "blendshapes", "--out", str(out)], src)
    head = json.loads((out / "avatar.json").read_text())
    return {
        "page_mb": round((out / "index.html").stat().st_size / 2**20, 2),
        "bin_mb": round((out / "avatar.bin").stat().st_size / 2**20, 2),
        "morph_encoding": head["driver"].get("morph_encoding"),
        "morph_deltas": head["sections"]["morph_deltas"]["shape"][0],
        "vertices": head["num_vertices"],
        "gaussians": head["num_gaussians"],
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run", type=Path, help="a trained blend-shape head's run folder")
    ap.add_argument("--before-src", type=Path, required=True, help="another checkout's src folder (the baseline)")
    ap.add_argument("--calls", type=int, default=15)
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    node = node_or_exit()
    work = Path(tempfile.mkdtemp(prefix="meshsplat-workers-"))
    try:
        pages = {"before": work / "before", "now": work / "now"}
        info = {
            name: write_page(args.run, d, args.before_src if name == "before" else None) for name, d in pages.items()
        }
        uris = {name: str(d) for name, d in pages.items()}
        (work / "job.mjs").write_text(NODE_JOB)
        r = subprocess.run(
            [node, str(work / "job.mjs"), json.dumps(uris), str(args.calls)], capture_output=True, text=True, check=True
        )
        times = json.loads(r.stdout)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    rows = {}
    print(f"{'page':>7} {'page MB':>8} {'deltas':>9} {'skin ms':>8} {'sortJob ms':>11} {'shadowJob ms':>13}")
    for name in pages:
        med = {k: (round(statistics.median(v), 2) if v else None) for k, v in times[name].items()}
        rows[name] = {**info[name], "median_ms": med, "ms": times[name]}
        print(
            f"{name:>7} {info[name]['page_mb']:8.1f} {info[name]['morph_deltas']:9d} {med['skin']:8.1f} "
            f"{med['sort']:11.1f} {med['shadow'] if med['shadow'] is not None else float('nan'):13.1f}"
        )
    out = args.out or results_path("viewer_workers")
    doc = {"machine": machine_info(), "run": args.run.name, "calls": args.calls, "pages": rows}
    out.write_text(json.dumps(doc, indent=1) + "\n")
    print("wrote", out.relative_to(ROOT) if out.is_relative_to(ROOT) else out)


if __name__ == "__main__":
    main()
