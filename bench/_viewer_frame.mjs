// Per-frame CPU time of the viewer under Node (used by bench/viewer.py).
// usage: node _viewer_frame.mjs VIEWER_JS BUNDLE_DIR new|old FRAMES  -> JSON medians in ms
import fs from "fs";
import path from "path";
import { pathToFileURL } from "url";

const [viewerJs, dir, mode, framesArg] = process.argv.slice(2);
const V = await import(pathToFileURL(viewerJs).href);
const header = JSON.parse(fs.readFileSync(path.join(dir, "avatar.json"), "utf8"));
const t0 = performance.now();
const b = V.decodeBundle(header, fs.readFileSync(path.join(dir, "avatar.bin")));
const decodeMs = performance.now() - t0;
const frames = parseInt(framesArg, 10);
const cam = header.camera;
const median = (a) => { const s = [...a].sort((x, y) => x - y); return s[Math.floor(s.length / 2)]; };
const main = [], sort = [];
const warm = 5;
if (mode === "new") {
  // main thread: FramePoser (vertex frames: decode the frame; live glTF: evaluate the clip);
  // worker: sortJob (skinning for live glTF, vertex normals, centre depths, counting sort)
  const poser = new V.FramePoser(b);
  const S = V.sortScratch(V.sortSetup(b));
  const live = b.driver.kind === "gltf";
  const clip = live ? b.rig.clips[0] : null;
  for (let i = 0; i < frames + warm; i++) {
    const vm = V.orbitViewmat(cam.center, cam.distance, cam.azimuth_deg + i, cam.elevation_deg);
    const a = performance.now();
    const pose = live ? poser.rig(0, clip.start + (i / 25) % clip.duration, null) : poser.frame(i % b.T);
    const m = performance.now() - a;
    const c = performance.now();
    V.sortJob(S, { id: i, viewmat: vm, ...(live ? { rig: pose.rig } : { verts: pose.verts }) });
    const s = performance.now() - c;
    if (i >= warm) { main.push(m); sort.push(s); }
  }
} else {
  const order = new Uint32Array(b.N), counts = new Uint32Array(65536), data = new Float32Array(b.N * 13);
  let posed = null;
  for (let i = 0; i < frames + warm; i++) {
    const vm = V.orbitViewmat(cam.center, cam.distance, cam.azimuth_deg + i, cam.elevation_deg);
    const a = performance.now();
    posed = V.poseGaussians(b, i % b.T, null, posed);
    const c = performance.now();
    const n = V.sortByDepth(posed.means, b.N, vm, order, counts);
    const s = performance.now() - c;
    for (let k = 0; k < n; k++) { // SplatRenderer.upload's packing
      const g = order[k], o = 13 * k;
      data[o] = posed.means[3 * g]; data[o + 1] = posed.means[3 * g + 1]; data[o + 2] = posed.means[3 * g + 2];
      for (let j = 0; j < 6; j++) data[o + 3 + j] = posed.cov[6 * g + j];
      data[o + 9] = b.rgb[3 * g]; data[o + 10] = b.rgb[3 * g + 1]; data[o + 11] = b.rgb[3 * g + 2];
      data[o + 12] = b.opacity[g];
    }
    const m = performance.now() - a;
    if (i >= warm) { main.push(m); sort.push(s); }
  }
}
console.log(JSON.stringify({ main_ms: median(main), sort_ms: median(sort), main_min_ms: Math.min(...main),
  sort_min_ms: Math.min(...sort), main_p90_ms: [...main].sort((x, y) => x - y)[Math.floor(0.9 * main.length)],
  decode_ms: decodeMs, frames: main.length }));
