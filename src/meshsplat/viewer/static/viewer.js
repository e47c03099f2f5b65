// meshsplat WebGL2 viewer: poses and shades mesh-embedded Gaussians on the GPU every frame and splats them.
//
// Per frame the main thread does per-vertex (vertex frames: decode the frame) or per-joint (live
// glTF: evaluate the clip) work only and uploads it to float textures. GPU passes then skin the
// mesh (live glTF), compute per-face rotations and area ratios and per-vertex normals and
// quaternions; the splat vertex shader evaluates each Gaussian's embedding (Phong point + d*n,
// blended rotation, area scale) and colour (view-dependent SH, learned irradiance of the posed
// normal, the key light shadowed by the posed mesh) and projects it; one instanced draw call, blended
// unclamped into a half-float target, then one full-screen pass clamps the image into the canvas. The key
// light's height maps (model.occlusion=key; one per direction over a soft key's disk) are built per pose on
// the CPU in a second Web Worker (keyShadowMap, ShadowMapper) and uploaded; while playing they may trail
// the drawn pose by a frame or two. The depth sort runs in a Web Worker (created from a Blob URL of inline
// source, so it works from file://) with a 16-bit counting sort; the main thread never waits for either.
//
// The exported functions (decodeBundle, frameVertices, evalRig, skinVertices, sortJob, orbitViewmat,
// intrinsics, ...) run under Node for the tests (tests/viewer_reference.mjs holds the CPU reference
// of the GPU posing) and bench/viewer.py. The UI starts only in a page that holds the embedded
// avatar data. Cameras follow the project convention: world->camera viewmat in OpenCV axes (x right,
// y down, z forward), pinhole K, pixel centres at +0.5. Matrices are row-major flat arrays.

export const SH_C0 = 0.28209479177387814;
export const EPS = 1e-12;     // meshsplat.mesh.geometry._EPS
const EPS2D = 0.3;            // 2D covariance dilation (pixels^2), as the rasterizer
const ALPHA_THRESHOLD = 1 / 255;
const ALPHA_MAX = 0.999;
const MAX_EXTEND = 3.33;
const FOV_CLAMP_MARGIN = 0.3;
export const NEAR_PLANE = 0.01;  // as meshsplat.render.rasterize's near_plane (the worker gets it too)
const SH_C1 = 0.4886025119029199;   // SH constants of meshsplat.gaussians.compose and .shading
const SH_C2 = [1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396];
const SH_C3 = [-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
               -0.4570457994644658, 1.445305721320277, -0.5900435899266435];
const SH9 = [0.28209479177387814, 0.4886025119029199, 1.0925484305920792, 0.31539156525252005, 0.5462742152960396];
export const TEX_WIDTH = 2048; // width of every data texture (texel i at (i % W, i / W))

// ------------------------------------------------------------------ bundle decoding
const TYPED = { float32: Float32Array, uint32: Uint32Array, int16: Int16Array, int32: Int32Array };

/** Float value of the IEEE half float bits `h` (as GLSL unpackHalf2x16). */
export function halfToFloat(h) {
  const s = h & 0x8000 ? -1 : 1, e = (h >>> 10) & 0x1f, m = h & 0x3ff;
  if (e === 0) return s * m * 5.960464477539063e-8; // 2^-24
  if (e === 31) return m ? NaN : s * Infinity;
  return s * (1 + m / 1024) * 2 ** (e - 15);
}

/** Float arrays of the packed Gaussians [N*8] words (layout: bundle.py pack_gaussians). */
export function unpackGaussians(packed, N) {
  const out = { face: new Uint32Array(N), uv: new Float32Array(2 * N), d: new Float32Array(N),
                opacity: new Float32Array(N), rgb: new Float32Array(3 * N), rot: new Float32Array(4 * N),
                scale: new Float32Array(3 * N) };
  const lo = (w) => halfToFloat(w & 0xffff), hi = (w) => halfToFloat(w >>> 16);
  for (let g = 0; g < N; g++) {
    const o = 8 * g;
    out.face[g] = packed[o];
    out.uv[2 * g] = lo(packed[o + 1]); out.uv[2 * g + 1] = hi(packed[o + 1]);
    out.d[g] = lo(packed[o + 2]); out.opacity[g] = hi(packed[o + 2]);
    out.rgb[3 * g] = lo(packed[o + 3]); out.rgb[3 * g + 1] = hi(packed[o + 3]);
    out.rot[4 * g] = lo(packed[o + 4]); out.rot[4 * g + 1] = hi(packed[o + 4]);
    out.rot[4 * g + 2] = lo(packed[o + 5]); out.rot[4 * g + 3] = hi(packed[o + 5]);
    out.scale[3 * g] = lo(packed[o + 6]); out.scale[3 * g + 1] = hi(packed[o + 6]);
    out.scale[3 * g + 2] = lo(packed[o + 7]); out.rgb[3 * g + 2] = hi(packed[o + 7]);
  }
  return out;
}

/** Bytes the header's sections need (the end of the last one). */
export function bundleBytes(header) {
  let need = 0;
  for (const s of Object.values(header.sections || {})) {
    const count = s.shape.reduce((a, b) => a * b, 1);
    need = Math.max(need, s.offset + count * TYPED[s.dtype].BYTES_PER_ELEMENT);
  }
  return need;
}

/** Why `header` is not a page this viewer plays (a foreign or older page), or null. */
export function headerProblem(header) {
  if (!header || typeof header !== "object" || header.format !== "meshsplat-viewer" || !header.sections) {
    return "this is not a meshsplat player page (its data header is missing or foreign)";
  }
  if (header.version !== 3) {
    return `this page was written by another meshsplat (player data version ${header.version}; this player reads 3): write it again with meshsplat view`;
  }
  for (const [name, s] of Object.entries(header.sections)) {
    if (!TYPED[s.dtype] || !Array.isArray(s.shape)) return `this page's data header is damaged (section ${name})`;
  }
  return null;
}

/** Typed-array views of avatar.bin (`bytes`: ArrayBuffer or Uint8Array) laid out per `header`. */
export function decodeBundle(header, bytes) {
  const problem = headerProblem(header);
  if (problem) throw new Error(problem);
  const have = bytes.byteLength, need = bundleBytes(header);
  if (have < need) {
    throw new Error(`this page's avatar data is cut short (${have.toLocaleString("en")} of ${need.toLocaleString("en")} bytes): ` +
                    "the page was truncated (an interrupted download or copy?); get the whole file again");
  }
  // own copy at offset 0 so that every section is aligned (a Node Buffer may be a view into a pool)
  const buf = new Uint8Array(bytes instanceof ArrayBuffer ? new Uint8Array(bytes) : bytes).buffer;
  const arr = {};
  for (const [name, s] of Object.entries(header.sections)) {
    const T = TYPED[s.dtype];
    const count = s.shape.reduce((a, b) => a * b, 1);
    arr[name] = new T(buf, s.offset, count);
  }
  const N = header.num_gaussians;
  const b = {
    header, V: header.num_vertices, F: header.num_faces, N, T: header.num_frames,
    faces: arr.faces, cano: arr.canonical_vertices, frames: arr.frames, packed: arr.gaussians, shRest: arr.sh_rest,
    ...unpackGaussians(arr.gaussians, N),
  };
  // canonical per-face frames (constant) and areas
  const cf = faceGeometry(b, Float64Array.from(b.cano));
  b.canoFrames = cf.frames;
  b.canoAreas = cf.areas;
  b.driver = header.driver || { kind: "frames" };
  if (b.driver.kind === "gltf") b.rig = decodeRig(b.driver, arr);
  b.webcam = header.webcam ? decodeWebcam(header.webcam, arr) : null;
  return b;
}

/** Rig arrays of a live glTF bundle (layout: meshsplat/viewer/rig.py). */
function decodeRig(d, arr) {
  const clips = d.clips.map((c) => ({ ...c, channels: c.channels.map((ch) => ({
    ...ch, times: arr.anim_times.subarray(ch.t_off, ch.t_off + ch.count),
    values: arr.anim_values.subarray(ch.v_off, ch.v_off + ch.count * ch.width * (ch.interp === "CUBICSPLINE" ? 3 : 1)),
  })) }));
  // deltas [D*3]; sparse: each delta's target in its vertex's group [D] (its weight: weights[first weight + target]),
  // else (dense groups) vertex v's m-th delta is target m, at first delta + m * group size
  let deltas = arr.morph_deltas, deltaTarget = null;
  const sparse = d.morph_encoding === "float16-sparse";
  if (sparse || d.morph_encoding === "float16") { // [D, 2] words: x|y, z|0 half floats (sparse: z|target)
    const D = arr.morph_deltas.length / 2;
    deltas = new Float32Array(3 * D);
    if (sparse) deltaTarget = new Uint16Array(D);
    for (let i = 0, o = 0; i < arr.morph_deltas.length; i += 2, o += 3) {
      const a = arr.morph_deltas[i], c = arr.morph_deltas[i + 1];
      deltas[o] = halfToFloat(a & 0xffff); deltas[o + 1] = halfToFloat(a >>> 16); deltas[o + 2] = halfToFloat(c & 0xffff);
      if (sparse) deltaTarget[i >> 1] = c >>> 16;
    }
  }
  return { K: d.influences, P: d.num_pairs, nodes: d.num_nodes, base: arr.rig_base, pairIndex: arr.rig_pair_index,
           pairWeight: arr.rig_pair_weight, pairNode: arr.pair_node, pairIbm: arr.pair_ibm, parent: arr.node_parent,
           order: arr.node_order, rest: arr.node_rest, trs: arr.node_trs, matrixNodes: new Set(d.matrix_nodes),
           morphInfo: arr.morph_info, deltas, deltaTarget, defaultWeights: arr.morph_default_weights,
           groups: d.morph_groups, clips };
}

// ------------------------------------------------------------------ live glTF driver (as meshsplat.drivers.gltf)
function slerpXyzw(a, b, s, out) {
  let a0 = a[0], a1 = a[1], a2 = a[2], a3 = a[3], b0 = b[0], b1 = b[1], b2 = b[2], b3 = b[3];
  const na = Math.hypot(a0, a1, a2, a3), nb = Math.hypot(b0, b1, b2, b3);
  a0 /= na; a1 /= na; a2 /= na; a3 /= na; b0 /= nb; b1 /= nb; b2 /= nb; b3 /= nb;
  let d = a0 * b0 + a1 * b1 + a2 * b2 + a3 * b3;
  if (d < 0) { b0 = -b0; b1 = -b1; b2 = -b2; b3 = -b3; d = -d; }
  let wa, wb;
  if (d > 0.9995) { wa = 1 - s; wb = s; } else {
    const th = Math.acos(Math.min(d, 1)), st = Math.sin(th);
    wa = Math.sin((1 - s) * th) / st; wb = Math.sin(s * th) / st;
  }
  out[0] = wa * a0 + wb * b0; out[1] = wa * a1 + wb * b1; out[2] = wa * a2 + wb * b2; out[3] = wa * a3 + wb * b3;
  const n = Math.hypot(out[0], out[1], out[2], out[3]);
  for (let i = 0; i < 4; i++) out[i] /= n;
  return out;
}

/** Value of an animation channel at time `t` (clamped to its keys), as meshsplat.drivers.gltf_io.sample_channel. */
export function sampleChannel(ch, t) {
  const T = ch.times, V = ch.values, w = ch.width, cubic = ch.interp === "CUBICSPLINE", K = T.length;
  const value = (k) => cubic ? V.subarray((3 * k + 1) * w, (3 * k + 2) * w) : V.subarray(k * w, (k + 1) * w);
  if (K === 1 || t <= T[0]) return Float64Array.from(value(0));
  if (t >= T[K - 1]) return Float64Array.from(value(K - 1));
  let lo = 0, hi = K - 1; // largest k with T[k] <= t
  while (hi - lo > 1) { const mid = (lo + hi) >> 1; if (T[mid] <= t) lo = mid; else hi = mid; }
  const k = lo, dt = T[k + 1] - T[k], s = dt > 0 ? (t - T[k]) / dt : 0;
  if (ch.interp === "STEP") return Float64Array.from(V.subarray(k * w, (k + 1) * w));
  const out = new Float64Array(w);
  if (cubic) {
    const s2 = s * s, s3 = s2 * s;
    for (let i = 0; i < w; i++) {
      const p0 = V[(3 * k + 1) * w + i], m0 = dt * V[(3 * k + 2) * w + i];
      const p1 = V[(3 * k + 4) * w + i], m1 = dt * V[(3 * k + 3) * w + i];
      out[i] = (2 * s3 - 3 * s2 + 1) * p0 + (s3 - 2 * s2 + s) * m0 + (-2 * s3 + 3 * s2) * p1 + (s3 - s2) * m1;
    }
    if (ch.path === "rotation") { const n = Math.hypot(...out); for (let i = 0; i < w; i++) out[i] /= n; }
    return out;
  }
  if (ch.path === "rotation") return slerpXyzw(value(k), value(k + 1), s, out);
  for (let i = 0; i < w; i++) out[i] = (1 - s) * V[k * w + i] + s * V[(k + 1) * w + i];
  return out;
}

function trsMatrix(t, r, s, m, o) { // row-major 4x4 T R S into m at o (r: xyzw, normalized here)
  const n = Math.hypot(r[0], r[1], r[2], r[3]), x = r[0] / n, y = r[1] / n, z = r[2] / n, w = r[3] / n;
  const R = [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w),
             2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w),
             2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)];
  for (let i = 0; i < 3; i++) {
    for (let j = 0; j < 3; j++) m[o + 4 * i + j] = R[3 * i + j] * s[j];
    m[o + 4 * i + 3] = t[i];
  }
  m[o + 12] = 0; m[o + 13] = 0; m[o + 14] = 0; m[o + 15] = 1;
}

function mul4(a, ao, b, bo, out, oo) {
  for (let i = 0; i < 4; i++) for (let j = 0; j < 4; j++) {
    out[oo + 4 * i + j] = a[ao + 4 * i] * b[bo + j] + a[ao + 4 * i + 1] * b[bo + 4 + j]
      + a[ao + 4 * i + 2] * b[bo + 8 + j] + a[ao + 4 * i + 3] * b[bo + 12 + j];
  }
}

/**
 * Rig state of clip `clip` (index) at `time` seconds (clamped to the clip), with morph weights
 * `override` (Float64Array [num_morph_weights], NaN = from the clip) applied last, and `pose`
 * ({node, rotation: xyzw} or undefined) replacing that node's rotation:
 * { pairs: Float32Array [P*12] (rows 0..2 of world[pair_node] @ inverse bind), weights: Float32Array }.
 */
export function evalRig(rig, clip, time, override, out, pose) {
  const N = rig.nodes, local = Float64Array.from(rig.rest), world = new Float64Array(16 * N);
  const trs = new Map(), weights = Float64Array.from(rig.defaultWeights);
  const c = clip === null || clip === undefined ? null : rig.clips[clip];
  if (c) {
    for (const ch of c.channels) {
      const v = sampleChannel(ch, time);
      if (ch.path === "weights") {
        const g = rig.groups.find((gr) => gr.node === ch.node);
        if (g) for (let m = 0; m < g.count; m++) weights[g.weight_base + m] = v[m];
        continue;
      }
      if (rig.matrixNodes.has(ch.node)) continue;
      if (!trs.has(ch.node)) {
        const o = 10 * ch.node;
        trs.set(ch.node, [rig.trs.slice(o, o + 3), rig.trs.slice(o + 3, o + 7), rig.trs.slice(o + 7, o + 10)]);
      }
      trs.get(ch.node)[["translation", "rotation", "scale"].indexOf(ch.path)] = v;
    }
  }
  if (pose) { // a node's rotation (xyzw) and translation set last (the webcam's head pose)
    const o = 10 * pose.node;
    if (!trs.has(pose.node)) trs.set(pose.node, [rig.trs.slice(o, o + 3), rig.trs.slice(o + 3, o + 7), rig.trs.slice(o + 7, o + 10)]);
    trs.get(pose.node)[1] = pose.rotation;
    if (pose.translation) trs.get(pose.node)[0] = pose.translation;
  }
  for (const [i, [t, r, s]] of trs) trsMatrix(t, r, s, local, 16 * i);
  if (override) for (let i = 0; i < weights.length; i++) if (!Number.isNaN(override[i])) weights[i] = override[i];
  for (const i of rig.order) {
    const p = rig.parent[i];
    if (p < 0) world.set(local.subarray(16 * i, 16 * i + 16), 16 * i); else mul4(world, 16 * p, local, 16 * i, world, 16 * i);
  }
  out = out || { pairs: new Float32Array(12 * rig.P), weights: new Float32Array(weights.length) };
  const m = new Float64Array(16);
  for (let p = 0; p < rig.P; p++) {
    mul4(world, 16 * rig.pairNode[p], rig.pairIbm, 16 * p, m, 0);
    for (let j = 0; j < 12; j++) out.pairs[12 * p + j] = m[j];
  }
  out.weights.set(weights);
  return out;
}

/** Posed vertices [V*3] of a rig state: linear blend skinning of the morphed base (CPU; the page does it on the GPU). */
export function skinVertices(rig, state, V, out) {
  out = out || new Float32Array(3 * V);
  const K = rig.K, P = state.pairs, W = state.weights, info = rig.morphInfo, D = rig.deltas, T = rig.deltaTarget;
  for (let v = 0; v < V; v++) {
    let x = rig.base[3 * v], y = rig.base[3 * v + 1], z = rig.base[3 * v + 2];
    const m0 = info[4 * v], M = info[4 * v + 1], n = info[4 * v + 2], wb = info[4 * v + 3];
    for (let m = 0; m < M; m++) {
      const i = m0 + m * n, w = W[wb + (T ? T[i] : m)];
      if (w !== 0) { const o = 3 * i; x += w * D[o]; y += w * D[o + 1]; z += w * D[o + 2]; }
    }
    let ox = 0, oy = 0, oz = 0;
    for (let k = 0; k < K; k++) {
      const w = rig.pairWeight[K * v + k];
      if (w === 0) continue;
      const o = 12 * rig.pairIndex[K * v + k];
      ox += w * (P[o] * x + P[o + 1] * y + P[o + 2] * z + P[o + 3]);
      oy += w * (P[o + 4] * x + P[o + 5] * y + P[o + 6] * z + P[o + 7]);
      oz += w * (P[o + 8] * x + P[o + 9] * y + P[o + 10] * z + P[o + 11]);
    }
    out[3 * v] = ox; out[3 * v + 1] = oy; out[3 * v + 2] = oz;
  }
  return out;
}

/** Area-weighted unit vertex normals [V*3] of positions `p` (the worker's copy of poseMesh's normals). */
export function vertexNormals(faces, V, p, out) {
  out = out || new Float32Array(3 * V);
  out.fill(0);
  for (let k = 0; k < faces.length; k += 3) {
    const a = 3 * faces[k], b = 3 * faces[k + 1], c = 3 * faces[k + 2];
    const e0x = p[b] - p[a], e0y = p[b + 1] - p[a + 1], e0z = p[b + 2] - p[a + 2];
    const e2x = p[c] - p[a], e2y = p[c + 1] - p[a + 1], e2z = p[c + 2] - p[a + 2];
    const cx = e0y * e2z - e0z * e2y, cy = e0z * e2x - e0x * e2z, cz = e0x * e2y - e0y * e2x;
    out[a] += cx; out[a + 1] += cy; out[a + 2] += cz; out[b] += cx; out[b + 1] += cy; out[b + 2] += cz;
    out[c] += cx; out[c + 1] += cy; out[c + 2] += cz;
  }
  for (let i = 0; i < 3 * V; i += 3) {
    const r = 1 / Math.sqrt(Math.max(out[i] ** 2 + out[i + 1] ** 2 + out[i + 2] ** 2, 1e-24));
    out[i] *= r; out[i + 1] *= r; out[i + 2] *= r;
  }
  return out;
}

/** Vertices [V*3] (Float64Array) of frame `t`, dequantized when stored as int16. */
export function frameVertices(b, t, out) {
  const n = b.V * 3, base = t * n;
  out = out || new Float64Array(n);
  if (b.header.vertex_encoding === "int16") {
    const o = b.header.vertex_offset, s = b.header.vertex_step;
    for (let i = 0; i < n; i += 3) {
      out[i] = o[0] + b.frames[base + i] * s[0];
      out[i + 1] = o[1] + b.frames[base + i + 1] * s[1];
      out[i + 2] = o[2] + b.frames[base + i + 2] * s[2];
    }
  } else {
    for (let i = 0; i < n; i++) out[i] = b.frames[base + i];
  }
  return out;
}

// ------------------------------------------------------------------ mesh geometry
/** Per face: cross product (b-a)x(c-a) [F*3], area [F], frame columns (t, bt, n) [F*9], row-major. */
export function faceGeometry(b, p, out) {
  const F = b.F, f = b.faces;
  out = out || { cross: new Float64Array(F * 3), areas: new Float64Array(F), frames: new Float64Array(F * 9) };
  for (let k = 0; k < F; k++) {
    const ia = 3 * f[3 * k], ib = 3 * f[3 * k + 1], ic = 3 * f[3 * k + 2];
    const e0x = p[ib] - p[ia], e0y = p[ib + 1] - p[ia + 1], e0z = p[ib + 2] - p[ia + 2];
    const e2x = p[ic] - p[ia], e2y = p[ic + 1] - p[ia + 1], e2z = p[ic + 2] - p[ia + 2];
    const cx = e0y * e2z - e0z * e2y, cy = e0z * e2x - e0x * e2z, cz = e0x * e2y - e0y * e2x;
    const c2 = cx * cx + cy * cy + cz * cz;
    out.cross[3 * k] = cx; out.cross[3 * k + 1] = cy; out.cross[3 * k + 2] = cz;
    out.areas[k] = 0.5 * Math.sqrt(Math.max(c2, EPS * EPS));
    const e02 = e0x * e0x + e0y * e0y + e0z * e0z, e22 = e2x * e2x + e2y * e2y + e2z * e2z;
    const m = out.frames, o = 9 * k;
    if (c2 > 1e-10 * e02 * e22 && e02 * e22 > 0) {
      const rt = 1 / Math.sqrt(Math.max(e02, EPS * EPS)), rn = 1 / Math.sqrt(Math.max(c2, EPS * EPS));
      const tx = e0x * rt, ty = e0y * rt, tz = e0z * rt, nx = cx * rn, ny = cy * rn, nz = cz * rn;
      const bx = ny * tz - nz * ty, by = nz * tx - nx * tz, bz = nx * ty - ny * tx; // n x t
      m[o] = tx; m[o + 1] = bx; m[o + 2] = nx;
      m[o + 3] = ty; m[o + 4] = by; m[o + 5] = ny;
      m[o + 6] = tz; m[o + 7] = bz; m[o + 8] = nz;
    } else { // degenerate face: identity frame
      m.fill(0, o, o + 9); m[o] = 1; m[o + 4] = 1; m[o + 8] = 1;
    }
  }
  return out;
}

// ------------------------------------------------------------------ key light shadow (as meshsplat.mesh.visibility)
const KEY_BIAS_CELLS = 0.75, KEY_SLOPE_CELLS = 1.5, KEY_MAX_TAN = 2.0; // meshsplat.mesh.visibility._BIAS_CELLS, ...
export const KEY_EMPTY = -3e38; // a cell no surface sample fell into (the Python grid's -inf): everything is lit there
export const KEY_MAX_MAPS = 12; // the most height maps a key's shadow averages (meshsplat.gaussians.shading.KEY_SOFT_SAMPLES)

/** Grid frame of a key light (unit `w`, `a`, `b`): (a, b) index the grid, w is the height towards the light. */
export function keyFrame(direction) {
  const n = Math.max(Math.hypot(direction[0], direction[1], direction[2]), 1e-12);
  const w = [direction[0] / n, direction[1] / n, direction[2] / n];
  const h = Math.abs(w[0]) < 0.9 ? [1, 0, 0] : [0, 1, 0]; // the helper vector
  const c = [h[1] * w[2] - h[2] * w[1], h[2] * w[0] - h[0] * w[2], h[0] * w[1] - h[1] * w[0]];
  const cn = Math.max(Math.hypot(c[0], c[1], c[2]), 1e-12);
  const a = [c[0] / cn, c[1] / cn, c[2] / cn];
  const b = [w[1] * a[2] - w[2] * a[1], w[2] * a[0] - w[0] * a[2], w[0] * a[1] - w[1] * a[0]];
  return { a, b, w };
}

/** The directions [S][3] whose height maps a key light's shadow averages (header.shading.key.shadows,
 * Shading.shadow_directions): its own, or a soft key's KEY_SOFT_SAMPLES directions over its disk. */
export function keyShadowDirections(key) {
  return key.shadows;
}

/**
 * The key light's height maps of the posed mesh (positions `p` [V*3]) exactly as
 * meshsplat.mesh.visibility.visibility builds them, one per keyShadowDirections(key): over the bounding
 * sphere of the vertices (centre = box centre, radius = half the box diagonal * 1.001 + 1e-12),
 * `grid` x `grid` cells of 2 radius / grid, each holding the largest height w.(x - centre) of the surface
 * samples over it (the vertices, plus a barycentric lattice with at most half a cell between neighbours on
 * each triangle with a longer edge); map s's cell (i, j) at depth[(s * grid + i) * grid + j], i along a,
 * j along b; -Infinity where none fell (uploaded as KEY_EMPTY). Returns { grid, depth, frame (the key's
 * own keyFrame), frames (one per map), centre, radius, cell, samples (per map) }. `out`: the previous
 * result to reuse (same key). CPU, float64.
 */
export function keyShadowMap(faces, V, p, key, out) {
  const grid = key.grid, dirs = keyShadowDirections(key), S = dirs.length;
  if (!out || out.grid !== grid || out.frames.length !== S) {
    out = { grid, depth: new Float64Array(S * grid * grid), frame: keyFrame(key.direction), frames: dirs.map(keyFrame) };
  }
  let lx = Infinity, ly = Infinity, lz = Infinity, hx = -Infinity, hy = -Infinity, hz = -Infinity;
  for (let v = 0; v < 3 * V; v += 3) {
    const x = p[v], y = p[v + 1], z = p[v + 2];
    if (x < lx) lx = x; if (x > hx) hx = x; if (y < ly) ly = y; if (y > hy) hy = y; if (z < lz) lz = z; if (z > hz) hz = z;
  }
  const cx = (lx + hx) / 2, cy = (ly + hy) / 2, cz = (lz + hz) / 2;
  const radius = Math.hypot(hx - lx, hy - ly, hz - lz) / 2 * 1.001 + 1e-12, cell = 2 * radius / grid;
  const samples = surfaceSamples(faces, V, p, [cx, cy, cz], cell / 2, out);
  const pts = out.pts, inv = 1 / cell, g1 = grid - 1, depth = out.depth;
  depth.fill(-Infinity);
  for (let s = 0; s < S; s++) { // each map: every sample's cell (a.(x - centre) + radius) / cell, (b. ...) and height w.(x - centre)
    const { a, b, w } = out.frames[s], o = s * grid * grid;
    const a0 = a[0], a1 = a[1], a2 = a[2], b0 = b[0], b1 = b[1], b2 = b[2], w0 = w[0], w1 = w[1], w2 = w[2];
    for (let m = 0; m < 3 * samples; m += 3) {
      const x = pts[m], y = pts[m + 1], z = pts[m + 2];
      const gi = (a0 * x + a1 * y + a2 * z + radius) * inv, gj = (b0 * x + b1 * y + b2 * z + radius) * inv;
      const h = w0 * x + w1 * y + w2 * z;
      const i = gi < 0 ? 0 : gi >= grid ? g1 : gi | 0, j = gj < 0 ? 0 : gj >= grid ? g1 : gj | 0, k = o + i * grid + j;
      if (h > depth[k]) depth[k] = h;
    }
  }
  Object.assign(out, { centre: [cx, cy, cz], radius, cell, samples });
  return out;
}

/**
 * The surface samples of meshsplat.mesh.visibility.surface_samples, less `centre` [3], into `out.pts`
 * (grown as needed): the vertices of `p` [V*3], then on each triangle (a, b, c) with an edge longer than
 * `spacing` the barycentric lattice of s = ceil(longest edge / spacing) steps, (i/s) a + (j/s) b +
 * ((s-i-j)/s) c, its corners left out. Returns the sample count.
 */
function surfaceSamples(faces, V, p, centre, spacing, out) {
  let n = V, pts = out.pts && out.pts.length >= 3 * V ? out.pts : (out.pts = new Float64Array(Math.max(3 * V, 1024)));
  const ox = centre[0], oy = centre[1], oz = centre[2];
  for (let v = 0; v < 3 * V; v += 3) { pts[v] = p[v] - ox; pts[v + 1] = p[v + 1] - oy; pts[v + 2] = p[v + 2] - oz; }
  for (let f = 0; f < faces.length; f += 3) {
    const ia = 3 * faces[f], ib = 3 * faces[f + 1], ic = 3 * faces[f + 2];
    const ax = p[ia], ay = p[ia + 1], az = p[ia + 2], bx = p[ib], by = p[ib + 1], bz = p[ib + 2];
    const cx = p[ic], cy = p[ic + 1], cz = p[ic + 2];
    const e2 = Math.max((ax - cx) ** 2 + (ay - cy) ** 2 + (az - cz) ** 2, (bx - ax) ** 2 + (by - ay) ** 2 + (bz - az) ** 2,
                        (cx - bx) ** 2 + (cy - by) ** 2 + (cz - bz) ** 2);
    const st = Math.max(1, Math.ceil(Math.sqrt(e2) / spacing)); // the longest edge, in lattice steps
    if (!(st > 1)) continue;
    const need = 3 * (n + (st + 1) * (st + 2) / 2 - 3);
    if (need > pts.length) { const grown = new Float64Array(Math.max(need, 2 * pts.length)); grown.set(pts); pts = out.pts = grown; }
    for (let i = 0; i <= st; i++) {
      for (let j = i === 0 ? 1 : 0, jn = i === st ? -1 : st - i - (i === 0 ? 1 : 0); j <= jn; j++) { // no corners
        const u = i / st, v = j / st, w = (st - i - j) / st;
        pts[3 * n] = u * ax + v * bx + w * cx - ox; pts[3 * n + 1] = u * ay + v * by + w * cy - oy;
        pts[3 * n + 2] = u * az + v * bz + w * cz - oz;
        n++;
      }
    }
  }
  return n;
}

/**
 * Visibility from the key light of a surface point `x` [3] with unit normal `n` [3] (the Phong normal,
 * for the slope-scaled bias) in a keyShadowMap `m`: the mean over its maps of lit (1) or not (0); the
 * splat shader's keyVisible on the CPU.
 */
export function keyVisibility(m, x, n) {
  const g1 = m.grid - 1, inv = 1 / m.cell, S = m.frames.length;
  const rx = x[0] - m.centre[0], ry = x[1] - m.centre[1], rz = x[2] - m.centre[2];
  let lit = 0;
  for (let s = 0; s < S; s++) {
    const { a, b, w } = m.frames[s];
    let i = Math.floor((a[0] * rx + a[1] * ry + a[2] * rz + m.radius) * inv);
    let j = Math.floor((b[0] * rx + b[1] * ry + b[2] * rz + m.radius) * inv);
    i = i < 0 ? 0 : i > g1 ? g1 : i; j = j < 0 ? 0 : j > g1 ? g1 : j;
    const cos = Math.min(Math.max(Math.abs(n[0] * w[0] + n[1] * w[1] + n[2] * w[2]), 1e-6), 1);
    const tan = Math.min(Math.sqrt(Math.max(1 - cos * cos, 0)) / cos, KEY_MAX_TAN);
    const bias = m.cell * (KEY_BIAS_CELLS + KEY_SLOPE_CELLS * tan);
    if (w[0] * rx + w[1] * ry + w[2] * rz >= m.depth[(s * m.grid + i) * m.grid + j] - bias) lit++;
  }
  return lit / S;
}

// ------------------------------------------------------------------ jobs in Web Workers (depth sort, shadow maps)
/** The posed vertices of `pose` ({verts} float32 [V*3], copied, or a {rig} state) into the message `msg`;
 * returns the buffers to transfer. */
function poseMessage(pose, msg) {
  if (pose.verts) { msg.verts = pose.verts.slice(); return [msg.verts.buffer]; }
  msg.rig = { pairs: pose.rig.pairs.slice(), weights: pose.rig.weights.slice() };
  return [];
}

/**
 * One job at a time in a Web Worker started from the inline `source` (a Blob URL, so that it works under
 * file://; it answers "init" with the static `setup`, "recycle" with a buffer to reuse, and any other
 * message with job's result), else (no Web Worker, `?worker=0`, or after a worker failure) the same
 * `job(state, msg)` on the calling thread, `state = scratch(setup)`. `onResult(r)` gets each result,
 * with `ms` (the job's time), or null when a request was lost. `what` names the job in console messages.
 */
class WorkerJob {
  constructor(what, source, setup, job, scratch, onResult, useWorker) {
    Object.assign(this, { what, setup, job, scratch, onResult, busy: false, nextId: 1, inWorker: false, S: null });
    try {
      if (!useWorker) throw new Error("disabled by ?worker=0");
      const url = URL.createObjectURL(new Blob([source], { type: "text/javascript" }));
      this.worker = new Worker(url);
      this.worker.onmessage = (e) => { this.busy = false; this.onResult(e.data); };
      this.worker.onerror = (e) => { // fall back to this thread
        console.error(`worker ${what}:`, e.message); this.worker = null; this.inWorker = false; this.busy = false;
        this.onResult(null); // the pending request is lost: ask again
      };
      this.worker.postMessage({ type: "init", setup });
      this.inWorker = true;
    } catch (err) {
      if (useWorker) console.warn(`no Web Worker, ${what} on the main thread:`, err);
      this.worker = null;
    }
  }

  /** The job's state on this thread (made once, also after a worker failure). */
  local() { return this.S || (this.S = this.scratch(this.setup)); }

  /** Give a result's buffer back once it has been uploaded (saves an allocation). */
  recycle(buffer) {
    if (this.worker) this.worker.postMessage({ type: "recycle", buffer }, [buffer.buffer]);
    else this.local().spare.push(buffer);
  }

  /** Run the job on `msg` (given an id), in the worker (`transfer`: its buffers) or here. */
  run(msg, transfer) {
    msg.id = this.nextId++;
    this.busy = true;
    if (this.worker) {
      this.worker.postMessage(msg, transfer);
    } else {
      const t0 = performance.now();
      const r = this.job(this.local(), msg);
      r.ms = performance.now() - t0;
      this.busy = false;
      this.onResult(r);
    }
    return msg.id;
  }
}

/**
 * Inline source of a WorkerJob's worker (it can then start from a Blob URL under file://): the constants
 * `consts` ({name: value}), the functions `fns` (job and scratch among them), and the protocol WorkerJob
 * speaks: "init" makes the state `scratch(setup)` (no scratch: the setup itself), "recycle" hands a
 * result buffer back to `S.spare`,
 * any other message runs `job(S, msg)` and posts its result with `ms`, transferring `r[result].buffer`.
 */
function workerSource(consts, fns, job, scratch, result) {
  return `"use strict";
${Object.entries(consts).map(([k, v]) => `const ${k} = ${v};`).join("\n")}
${fns.map((f) => f.toString()).join("\n")}
let S = null;
onmessage = (e) => {
  if (e.data.type === "init") { S = ${scratch ? scratch.name : ""}(e.data.setup); return; }
  if (e.data.type === "recycle") { S.spare.push(e.data.buffer); return; }
  const t0 = performance.now();
  const r = ${job.name}(S, e.data);
  r.ms = performance.now() - t0;
  postMessage(r, [r.${result}.buffer]);
};
`;
}

// ------------------------------------------------------------------ key light height maps off the main thread
/**
 * The shadow worker's job for one pose: posed vertices (given, or skinned from a rig state as the GPU
 * pass does), keyShadowMap, and its depths as the float32 texture data the page uploads (KEY_EMPTY where
 * no sample fell). `S` holds the static data (faces, V, key, rig) and the reused map and spare buffers.
 * Returns { id, depth (Float32Array), centre, radius, cell, samples }.
 */
export function shadowJob(S, msg) {
  const verts = msg.verts || (S.skinned = skinVertices(S.rig, msg.rig, S.V, S.skinned));
  const m = S.map = keyShadowMap(S.faces, S.V, verts, S.key, S.map);
  const d = m.depth, out = S.spare.pop() || new Float32Array(d.length);
  for (let i = 0; i < d.length; i++) out[i] = d[i] === -Infinity ? KEY_EMPTY : d[i];
  return { id: msg.id, depth: out, centre: m.centre, radius: m.radius, cell: m.cell, samples: m.samples };
}

/** Static data for shadowJob from a decoded bundle with a key light (what the worker receives once). */
export function shadowSetup(b) {
  return { faces: b.faces, V: b.V, key: b.header.shading.key, rig: b.rig ? { ...b.rig, clips: null } : null, spare: [] };
}

/** Source of the shadow worker (inline, so that it can start from a Blob URL under file://). */
export const SHADOW_WORKER_SOURCE = workerSource(
  { KEY_EMPTY }, [skinVertices, keyFrame, keyShadowDirections, keyShadowMap, surfaceSamples, shadowJob],
  shadowJob, null, "depth");

/**
 * The key light's height maps of each new pose (shadowJob), built in a Web Worker when available (the
 * main thread only uploads them), else on the calling thread. `onResult(r)` as WorkerJob's.
 */
export class ShadowMapper extends WorkerJob {
  constructor(b, onResult, useWorker = true) {
    super("building the shadow maps", SHADOW_WORKER_SOURCE, shadowSetup(b), shadowJob, (setup) => setup, onResult, useWorker);
  }

  /** Ask for the height maps of a pose ({verts} float32 [V*3] or {rig} state); false when busy. */
  request(pose) {
    if (this.busy) return false;
    const msg = { type: "map" };
    return this.run(msg, poseMessage(pose, msg));
  }
}

// ------------------------------------------------------------------ cameras (as meshsplat.synth.rigs)
/**
 * World->camera [16] row-major (OpenCV axes) of a camera orbiting `center` (angles in degrees) about
 * `up` (default +y), azimuth 0 at `front` (default +z; both orthonormal, as the bundle's camera stores them).
 */
export function orbitViewmat(center, distance, azimuthDeg, elevationDeg, up = [0, 1, 0], front = [0, 0, 1]) {
  const az = azimuthDeg * Math.PI / 180, el = elevationDeg * Math.PI / 180;
  const norm = (a) => { const l = Math.hypot(a[0], a[1], a[2]); return [a[0] / l, a[1] / l, a[2] / l]; };
  const cross = (a, c) => [a[1] * c[2] - a[2] * c[1], a[2] * c[0] - a[0] * c[2], a[0] * c[1] - a[1] * c[0]];
  const side = cross(up, front);
  const a = Math.cos(el) * Math.sin(az), b = Math.sin(el), c = Math.cos(el) * Math.cos(az);
  const eye = [0, 1, 2].map((k) => center[k] + distance * (a * side[k] + b * up[k] + c * front[k]));
  const fwd = norm([center[0] - eye[0], center[1] - eye[1], center[2] - eye[2]]);
  let right = cross(fwd, up);
  if (Math.hypot(right[0], right[1], right[2]) < 1e-8) right = cross(fwd, [0, 0, 1]);
  right = norm(right);
  const down = cross(fwd, right);
  const R = [right, down, fwd];
  const m = new Float64Array(16);
  for (let i = 0; i < 3; i++) {
    m[4 * i] = R[i][0]; m[4 * i + 1] = R[i][1]; m[4 * i + 2] = R[i][2];
    m[4 * i + 3] = -(R[i][0] * eye[0] + R[i][1] * eye[1] + R[i][2] * eye[2]);
  }
  m[15] = 1;
  return m;
}

/**
 * The page's current view as a URL fragment value, `view=AZ,EL,DIST,CX,CY,CZ,FOV,W,H` (degrees, the
 * orbit's distance and centre in the avatar's units, the canvas in pixels): what
 * `meshsplat render --camera 'page:FOLDER#view=...'` draws (meshsplat.viewer.bundle.page_camera).
 */
export function viewString(cam, fovDeg, width, height) {
  const n = (x) => String(Number(Number(x).toPrecision(10)));
  return `view=${[cam.az, cam.el, cam.dist, ...cam.center, fovDeg].map(n).join(",")},${width},${height}`;
}

/** {az, el, dist, center, fov, width, height} of a `view=...` string (with or without '#'), or null. */
export function parseView(text) {
  const m = /(?:^|[#&])view=([-+0-9.eE,]+)/.exec(text || "");
  if (!m) return null;
  const v = m[1].split(",").map(Number);
  if (v.length !== 9 || !v.every(Number.isFinite) || !(v[2] > 0)) return null;
  return { az: v[0], el: v[1], dist: v[2], center: [v[3], v[4], v[5]], fov: v[6], width: v[7], height: v[8] };
}

/** The view's render flags (meshsplat render / view). */
export function viewFlags(cam, fovDeg, width, height) {
  const n = (x) => String(Number(Number(x).toPrecision(7)));
  return `--azimuth ${n(cam.az)} --elevation ${n(cam.el)} --distance ${n(cam.dist)} --center ${cam.center.map(n).join(",")} ` +
         `--fov ${n(fovDeg)} --size ${width}x${height}`;
}

/** Pinhole [fx, fy, cx, cy] for a vertical field of view, principal point at the image centre. */
export function intrinsics(width, height, fovDeg) {
  const f = 0.5 * height / Math.tan(fovDeg * Math.PI / 360);
  return [f, f, width / 2, height / 2];
}

/** Above this many Gaussians the sort key skips renormalizing the interpolated normal (speed). */
export const EXACT_KEY_MAX = 200000;

/**
 * Per-vertex camera depth z_v and camera z of the normal (and, when `exact`, the normal) in
 * `g.pv` (stride 5 or 2), and `g.corners`: stride * vertex index of each Gaussian's corners (cached).
 */
export function vertexKeys(g, verts, normals, viewmat, exact) {
  const N = g.N, V = verts.length / 3, S = exact ? 5 : 2, f = g.faces, face = g.face;
  const r0 = viewmat[8], r1 = viewmat[9], r2 = viewmat[10], t = viewmat[11];
  if (!g.corners || g.corners.length !== 3 * N || g.stride !== S) {
    g.corners = new Uint32Array(3 * N); g.stride = S;
    for (let i = 0; i < N; i++) for (let j = 0; j < 3; j++) g.corners[3 * i + j] = S * f[3 * face[i] + j];
  }
  if (!g.pv || g.pv.length !== S * V) g.pv = new Float32Array(S * V); // float32: half the cache footprint
  const pv = g.pv;
  for (let v = 0; v < V; v++) {
    const x = normals[3 * v], y = normals[3 * v + 1], z = normals[3 * v + 2];
    pv[S * v] = r0 * verts[3 * v] + r1 * verts[3 * v + 1] + r2 * verts[3 * v + 2] + t;
    pv[S * v + 1] = r0 * x + r1 * y + r2 * z;
    if (exact) { pv[S * v + 2] = x; pv[S * v + 3] = y; pv[S * v + 4] = z; }
  }
  return { pv, cn: g.corners, S };
}

/**
 * The worker's sort in two passes over the Gaussians: the key of gaussianDepths quantized at once
 * to 16 bits over a range bounded from the vertices ([min z_v - |d|max, max z_v + |d|max], clamped,
 * nearer than NEAR_PLANE dropped) and counted; then a stable back-to-front scatter into `order`.
 * `moved`: bound on how far any key moved since the previous call, from the vertices:
 * baryMax max|Δz_v| + |d|max max|Δ(r3.n_v)| (Infinity on the first call). `ws`: scratch.
 */
export function sortGaussians(g, verts, normals, viewmat, order, ws) {
  const N = g.N, uv = g.uv, dd = g.d, exact = N <= EXACT_KEY_MAX;
  if (g.dMax === undefined) {
    let dMax = 0, baryMax = 1;
    for (let i = 0; i < N; i++) {
      const u = uv[2 * i], v = uv[2 * i + 1];
      dMax = Math.max(dMax, Math.abs(dd[i]));
      baryMax = Math.max(baryMax, Math.abs(u) + Math.abs(v) + Math.abs(1 - u - v));
    }
    g.dMax = dMax; g.baryMax = baryMax;
  }
  const { pv, cn, S } = vertexKeys(g, verts, normals, viewmat, exact);
  const V = pv.length / S, prev = g.prevKeys;
  let zmin = Infinity, zmax = -Infinity, dz = 0, dn = 0;
  for (let v = 0; v < V; v++) {
    const z = pv[S * v];
    if (z < zmin) zmin = z; if (z > zmax) zmax = z;
    if (prev && prev.length === 2 * V) {
      dz = Math.max(dz, Math.abs(z - prev[2 * v])); dn = Math.max(dn, Math.abs(pv[S * v + 1] - prev[2 * v + 1]));
    }
  }
  const moved = prev && prev.length === 2 * V ? g.baryMax * dz + g.dMax * dn : Infinity;
  if (!prev || prev.length !== 2 * V) g.prevKeys = new Float64Array(2 * V);
  for (let v = 0; v < V; v++) { g.prevKeys[2 * v] = pv[S * v]; g.prevKeys[2 * v + 1] = pv[S * v + 1]; }
  const lo = Math.max(NEAR_PLANE, zmin - g.dMax), hi = Math.max(lo + 1e-12, zmax + g.dMax), q = 65535 / (hi - lo);
  const counts = ws.counts, bins = ws.bins && ws.bins.length >= N ? ws.bins : (ws.bins = new Int32Array(N));
  counts.fill(0);
  for (let i = 0; i < N; i++) {
    const u = uv[2 * i], v = uv[2 * i + 1], w = 1 - u - v;
    const a = cn[3 * i], b = cn[3 * i + 1], c = cn[3 * i + 2];
    let s = dd[i];
    if (exact) {
      const nx = u * pv[a + 2] + v * pv[b + 2] + w * pv[c + 2];
      const ny = u * pv[a + 3] + v * pv[b + 3] + w * pv[c + 3];
      const nz = u * pv[a + 4] + v * pv[b + 4] + w * pv[c + 4];
      s /= Math.sqrt(Math.max(nx * nx + ny * ny + nz * nz, 1e-24));
    }
    const key = u * pv[a] + v * pv[b] + w * pv[c] + s * (u * pv[a + 1] + v * pv[b + 1] + w * pv[c + 1]);
    if (key >= NEAR_PLANE) {
      let x = (key - lo) * q;
      x = x < 0 ? 0 : x > 65535 ? 65535 : x;
      const bin = 65535 - (x | 0); // far first
      bins[i] = bin; counts[bin]++;
    } else bins[i] = -1;
  }
  let visible = 0;
  for (let i = 0; i < 65536; i++) { visible += counts[i]; counts[i] = visible; }
  for (let i = N - 1; i >= 0; i--) { const bin = bins[i]; if (bin >= 0) order[--counts[bin]] = i; }
  return { n: visible, lo, hi, moved };
}

// ------------------------------------------------------------------ sort worker
/** Texels of a TEX_WIDTH-wide texture holding `n` texels (whole rows). */
export function texSize(n) { return TEX_WIDTH * Math.max(1, Math.ceil(n / TEX_WIDTH)); }

/**
 * The worker's job for one pose: posed vertices (given, or skinned from a rig state), vertex
 * normals, Gaussian centre depths, 16-bit counting sort (sortGaussians). Also returns `moved`, a
 * bound on how far any centre's depth moved since the previous sort (a stale order's error, see docs).
 * `S` holds the static data (faces, face/uv/d of the Gaussians, rig) and scratch buffers.
 */
export function sortJob(S, msg) {
  const verts = msg.verts || skinVertices(S.rig, msg.rig, S.V, S.verts);
  const normals = vertexNormals(S.faces, S.V, verts, S.normals);
  const order = S.spare.pop() || new Uint32Array(S.N); // buffers come back from the main thread
  const r = sortGaussians(S, verts, normals, msg.viewmat, order, S.ws);
  return { id: msg.id, n: r.n, order, moved: r.moved, lo: r.lo, hi: r.hi };
}

/** Static data for sortJob from a decoded bundle (what the worker receives once). */
export function sortSetup(b) {
  return { N: b.N, V: b.V, faces: b.faces, face: b.face, uv: b.uv, d: b.d, rig: b.rig ? { ...b.rig, clips: null } : null };
}

export function sortScratch(S) {
  Object.assign(S, { verts: new Float32Array(3 * S.V), normals: new Float32Array(3 * S.V), spare: [],
                     ws: { counts: new Uint32Array(65536), bins: new Int32Array(S.N) } });
  return S;
}

/** Source of the sort worker (inline, so that it can start from a Blob URL under file://). */
export const SORT_WORKER_SOURCE = workerSource(
  { EXACT_KEY_MAX, NEAR_PLANE }, [skinVertices, vertexNormals, vertexKeys, sortGaussians, sortJob, sortScratch],
  sortJob, sortScratch, "order");

/** The depth sorter (sortJob): a Web Worker when available, else the calling thread (see WorkerJob). */
export class DepthSorter extends WorkerJob {
  constructor(b, onResult, useWorker = true) {
    super("sorting", SORT_WORKER_SOURCE, sortSetup(b), sortJob, sortScratch, onResult, useWorker);
  }

  /** Ask for a sort of a pose ({verts} float32 [V*3] or {rig} state) seen from `viewmat`; false when busy. */
  request(pose, viewmat) {
    if (this.busy) return false;
    const msg = { type: "sort", viewmat: Array.from(viewmat) };
    return this.run(msg, poseMessage(pose, msg));
  }
}

// ------------------------------------------------------------------ WebGL2: GPU posing passes
const TEXEL = `
ivec2 at(int i) { return ivec2(i & ${TEX_WIDTH - 1}, i >> ${Math.log2(TEX_WIDTH)}); }
int here() { return int(gl_FragCoord.y) * ${TEX_WIDTH} + int(gl_FragCoord.x); }`;

const PASS_VERT = `#version 300 es
layout(location=0) in vec2 corner;
void main() { gl_Position = vec4(corner, 0.0, 1.0); }`;

// pass A (live glTF): morph targets + linear blend skinning -> posed positions
const SKIN_FRAG = `#version 300 es
precision highp float; precision highp int; precision highp sampler2D; precision highp usampler2D;
uniform int count; uniform int K;
uniform sampler2D baseTex, deltaTex, weightTex, pairTex, jwTex;
uniform usampler2D morphTex, jiTex;
out vec4 o;${TEXEL}
void main() {
  int v = here();
  if (v >= count) { o = vec4(0.0); return; }
  vec3 p = texelFetch(baseTex, at(v), 0).xyz;
  uvec4 mi = texelFetch(morphTex, at(v), 0);       // first delta, count, group size, first weight
  for (uint m = 0u; m < mi.y; m++) {
    vec4 d = texelFetch(deltaTex, at(int(mi.x + m * mi.z)), 0);  // xyz, its target in the group (w)
    float w = texelFetch(weightTex, at(int(mi.w) + int(d.w)), 0).x;
    if (w != 0.0) p += w * d.xyz;
  }
  vec4 r0 = vec4(0.0), r1 = vec4(0.0), r2 = vec4(0.0);
  for (int t = 0; t < K / 4; t++) {
    uvec4 j = texelFetch(jiTex, at(v * (K / 4) + t), 0);
    vec4 w = texelFetch(jwTex, at(v * (K / 4) + t), 0);
    for (int c = 0; c < 4; c++) {
      if (w[c] == 0.0) continue;
      int q = 3 * int(j[c]);
      r0 += w[c] * texelFetch(pairTex, at(q), 0);
      r1 += w[c] * texelFetch(pairTex, at(q + 1), 0);
      r2 += w[c] * texelFetch(pairTex, at(q + 2), 0);
    }
  }
  vec4 h = vec4(p, 1.0);
  o = vec4(dot(r0, h), dot(r1, h), dot(r2, h), 1.0);
}`;

// pass B: per face of the posed mesh -> rotation from canonical (quaternion), cross/area, area ratio
const FACE_FRAG = `#version 300 es
precision highp float; precision highp int; precision highp sampler2D; precision highp usampler2D;
uniform int count;
uniform sampler2D pTex, cfTex; uniform usampler2D fTex;
layout(location=0) out vec4 oq; layout(location=1) out vec4 oc; layout(location=2) out vec4 or_;${TEXEL}
void main() {
  int k = here();
  if (k >= count) { oq = vec4(1.0, 0.0, 0.0, 0.0); oc = vec4(0.0); or_ = vec4(1.0); return; }
  uvec4 f = texelFetch(fTex, at(k), 0);
  vec3 a = texelFetch(pTex, at(int(f.x)), 0).xyz, b = texelFetch(pTex, at(int(f.y)), 0).xyz;
  vec3 c = texelFetch(pTex, at(int(f.z)), 0).xyz;
  vec3 e0 = b - a, e2 = c - a, cr = cross(e0, e2);
  float c2 = dot(cr, cr), e02 = dot(e0, e0), e22 = dot(e2, e2);
  float area = 0.5 * sqrt(max(c2, ${EPS * EPS}));
  vec3 t = vec3(1.0, 0.0, 0.0), bt = vec3(0.0, 1.0, 0.0), n = vec3(0.0, 0.0, 1.0);
  if (c2 > 1e-10 * e02 * e22 && e02 * e22 > 0.0) {
    t = e0 * inversesqrt(max(e02, ${EPS * EPS})); n = cr * inversesqrt(max(c2, ${EPS * EPS})); bt = cross(n, t);
  }
  // canonical frame rows (t_i, b_i, n_i) and area; R = F_posed F_cano^T, R_ij = sum_c Fp[i][c] Fc[j][c]
  vec4 c0 = texelFetch(cfTex, at(3 * k), 0), c1 = texelFetch(cfTex, at(3 * k + 1), 0), c2v = texelFetch(cfTex, at(3 * k + 2), 0);
  vec3 p0 = vec3(t.x, bt.x, n.x), p1 = vec3(t.y, bt.y, n.y), p2 = vec3(t.z, bt.z, n.z);
  float m00 = dot(p0, c0.xyz), m01 = dot(p0, c1.xyz), m02 = dot(p0, c2v.xyz);
  float m10 = dot(p1, c0.xyz), m11 = dot(p1, c1.xyz), m12 = dot(p1, c2v.xyz);
  float m20 = dot(p2, c0.xyz), m21 = dot(p2, c1.xyz), m22 = dot(p2, c2v.xyz);
  vec4 cand = vec4(1.0 + m00 + m11 + m22, 1.0 + m00 - m11 - m22, 1.0 - m00 + m11 - m22, 1.0 - m00 - m11 + m22);
  int best = 0;
  for (int i = 1; i < 4; i++) if (cand[i] > cand[best]) best = i;   // first maximum, as torch.argmax
  vec4 q;
  if (best == 0) q = vec4(cand.x, m21 - m12, m02 - m20, m10 - m01);
  else if (best == 1) q = vec4(m21 - m12, cand.y, m10 + m01, m02 + m20);
  else if (best == 2) q = vec4(m02 - m20, m10 + m01, cand.z, m12 + m21);
  else q = vec4(m10 - m01, m20 + m02, m21 + m12, cand.w);
  float r = 1.0 / max(length(q), 1e-12);
  if (q.x * r < 0.0) r = -r;
  oq = q * r;
  oc = vec4(cr, area);
  float a0 = c0.w;
  or_ = vec4(a0 > ${EPS} ? area / a0 : 1.0, 0.0, 0.0, 0.0);
}`;

// pass C: per vertex -> area-weighted normal, quaternion = sign-aligned area-weighted face quaternion sum
const VERTEX_FRAG = `#version 300 es
precision highp float; precision highp int; precision highp sampler2D; precision highp usampler2D;
uniform int count;
uniform sampler2D fqTex, fcTex; uniform usampler2D adjTex, vaTex;
layout(location=0) out vec4 on; layout(location=1) out vec4 oq;${TEXEL}
void main() {
  int v = here();
  if (v >= count) { on = vec4(0.0); oq = vec4(1.0, 0.0, 0.0, 0.0); return; }
  uvec4 ad = texelFetch(vaTex, at(v), 0);
  int start = int(ad.x), cnt = int(ad.y);
  vec3 ns = vec3(0.0); float wmax = -1.0; int ref = 0;
  for (int i = 0; i < cnt; i++) {           // faces in increasing index: ties -> largest face index
    int k = int(texelFetch(adjTex, at(start + i), 0).x);
    vec4 fc = texelFetch(fcTex, at(k), 0);
    ns += fc.xyz;
    if (fc.w >= wmax) { wmax = fc.w; ref = k; }
  }
  vec4 qr = texelFetch(fqTex, at(ref), 0), acc = vec4(0.0);
  for (int i = 0; i < cnt; i++) {
    int k = int(texelFetch(adjTex, at(start + i), 0).x);
    vec4 q = texelFetch(fqTex, at(k), 0);
    float w = texelFetch(fcTex, at(k), 0).w;
    acc += (dot(q, qr) < 0.0 ? -w : w) * q;
  }
  on = vec4(ns * inversesqrt(max(dot(ns, ns), ${EPS * EPS})), 0.0);
  float n2 = dot(acc, acc);
  oq = n2 > 1e-30 ? acc / max(sqrt(n2), 1e-15) : vec4(1.0, 0.0, 0.0, 0.0);
}`;

// ------------------------------------------------------------------ WebGL2 splatting
// pass C, per Gaussian (once per draw, not once per quad corner): posed mean, covariance, projection and
// colour -> its pixel position and radius, conic, colour and opacity (three RGBA32F texels); the draw's
// vertex shader (VERT) only places the quad's corners
const PREP_FRAG = `#version 300 es
precision highp float; precision highp int;
precision highp sampler2D; precision highp usampler2D;
uniform int count;
uniform usampler2D gTex;                // 2 RGBA32UI texels per Gaussian (bundle.py pack_gaussians)
uniform usampler2D shTex;               // shTexels RGBA32UI texels per Gaussian: SH bands > 0, half floats
uniform usampler2D fTex;                // face -> vertex indices (a, b, c)
uniform sampler2D pTex, nTex, qTex;     // per posed vertex: position, normal, quaternion wxyz
uniform sampler2D rTex;                 // per face: posed / canonical area (x)
uniform int scaleMode;                  // 0 none, 1 area, 2 sqrt_area
uniform int shK, shTexels, shFrame;     // SH coefficients above the DC (0, 3, 8, 15); frame: 0 world, 1 triangle
uniform int shadeNormal;                // learned irradiance: 0 off, 1 Phong normal, 2 shortest axis
uniform vec3 irr[9];                    // its SH coefficients (world space, per channel)
uniform bool specular;                  // an added SH2 term of the same normal (model.specular=sh2)
uniform vec3 spec[9];                   // its SH coefficients (world space, per channel)
uniform bool keyOn;                     // the shadowed key light (model.occlusion=key): E += L V(x) max(0, n . w)
uniform vec3 keyLight, keyDir;          // L (RGB); w, towards the light
uniform vec3 keyA[${KEY_MAX_MAPS}], keyB[${KEY_MAX_MAPS}], keyW[${KEY_MAX_MAPS}]; // each height map's frame (a, b, w)
uniform int keyMaps;                    // how many height maps the shadow averages (1: a hard shadow)
uniform vec3 keyCentre;                 // the posed mesh's bounding-sphere centre (this frame)
uniform float keyRadius, keyCell;       // its radius, the cell size 2 radius / grid
uniform int keyGrid;
uniform sampler2D kTex;                 // keyMaps grid x grid heights (R32F) stacked: map s's cell (i, j) at (j, s grid + i)
uniform bool antialiased;               // opacity x sqrt(det S / det(S + eps I))
uniform mat3 R; uniform vec3 tr;        // world->camera (OpenCV)
uniform vec4 K;                         // fx, fy, cx, cy
uniform vec2 size;                      // width, height (pixels)
layout(location=0) out vec4 oPos;       // pixel position (y down), the quad's first half-axis u (pixels)
layout(location=1) out vec4 oConic;     // conic (inverse 2D covariance: a, b, c), the second half-axis's length
                                        // (along u turned 90°; < 0: not drawn)
layout(location=2) out vec4 oCol;       // colour, opacity${TEXEL}
vec4 quatMul(vec4 a, vec4 b) {          // Hamilton product, w first
  return vec4(a.x * b.x - dot(a.yzw, b.yzw), a.x * b.yzw + b.x * a.yzw + cross(a.yzw, b.yzw));
}
mat3 quatMat(vec4 q) {                  // rotation of a unit wxyz quaternion (GLSL: columns)
  float qw = q.x, qx = q.y, qy = q.z, qz = q.w;
  return mat3(1.0 - 2.0 * (qy * qy + qz * qz), 2.0 * (qx * qy + qw * qz), 2.0 * (qx * qz - qw * qy),
              2.0 * (qx * qy - qw * qz), 1.0 - 2.0 * (qx * qx + qz * qz), 2.0 * (qy * qz + qw * qx),
              2.0 * (qx * qz + qw * qy), 2.0 * (qy * qz - qw * qx), 1.0 - 2.0 * (qx * qx + qy * qy));
}
// colour = max(0, 0.5 + SH(view direction)) (meshsplat.gaussians.compose.eval_sh); dc = 0.5 + C0 sh0
vec3 viewColour(int g, vec3 dc, vec3 dir) {
  float c[45];
  for (int t = 0; t < shTexels; t++) {
    uvec4 w = texelFetch(shTex, at(g * shTexels + t), 0);
    for (int j = 0; j < 4; j++) {
      int i = 8 * t + 2 * j;
      vec2 h = unpackHalf2x16(w[j]);
      if (i < 45) c[i] = h.x;
      if (i + 1 < 45) c[i + 1] = h.y;
    }
  }
  #define SH(k) vec3(c[3 * (k)], c[3 * (k) + 1], c[3 * (k) + 2])
  vec3 d = dir / max(length(dir), 1e-12);
  float x = d.x, y = d.y, z = d.z;
  vec3 rgb = dc - ${SH_C1} * y * SH(0) + ${SH_C1} * z * SH(1) - ${SH_C1} * x * SH(2);
  if (shK >= 8) {
    float xx = x * x, yy = y * y, zz = z * z;
    rgb += ${SH_C2[0]} * x * y * SH(3) + ${SH_C2[1]} * y * z * SH(4) + ${SH_C2[2]} * (2.0 * zz - xx - yy) * SH(5)
         + ${SH_C2[3]} * x * z * SH(6) + ${SH_C2[4]} * (xx - yy) * SH(7);
    if (shK >= 15) {
      rgb += ${SH_C3[0]} * y * (3.0 * xx - yy) * SH(8) + ${SH_C3[1]} * x * y * z * SH(9)
           + ${SH_C3[2]} * y * (4.0 * zz - xx - yy) * SH(10) + ${SH_C3[3]} * z * (2.0 * zz - 3.0 * xx - 3.0 * yy) * SH(11)
           + ${SH_C3[4]} * x * (4.0 * zz - xx - yy) * SH(12) + ${SH_C3[5]} * z * (xx - yy) * SH(13)
           + ${SH_C3[6]} * x * (xx - 3.0 * yy) * SH(14);
    }
  }
  return rgb;
}
// the mean over the height maps of 1 when the surface point x (unit Phong normal n) is not below its
// cell's height by more than the slope-scaled bias, else 0 (meshsplat.mesh.visibility.visibility, averaged
// over Shading.shadow_directions; keyVisibility in viewer.js)
float keyVisible(vec3 x, vec3 n) {
  vec3 r = x - keyCentre;
  float inv = 1.0 / keyCell;
  int g1 = keyGrid - 1;
  float lit = 0.0;
  for (int s = 0; s < ${KEY_MAX_MAPS}; s++) {
    if (s >= keyMaps) break;
    int i = clamp(int(floor((dot(keyA[s], r) + keyRadius) * inv)), 0, g1);
    int j = clamp(int(floor((dot(keyB[s], r) + keyRadius) * inv)), 0, g1);
    float c = clamp(abs(dot(n, keyW[s])), 1e-6, 1.0);
    float t = min(sqrt(max(1.0 - c * c, 0.0)) / c, ${KEY_MAX_TAN.toFixed(1)});
    float bias = keyCell * (${KEY_BIAS_CELLS} + ${KEY_SLOPE_CELLS} * t);
    if (dot(keyW[s], r) >= texelFetch(kTex, ivec2(j, s * keyGrid + i), 0).x - bias) lit += 1.0;
  }
  return lit / float(keyMaps);
}
// sum_i Y_i(n) c_i: the 9 real SH basis functions up to order 2 at n (meshsplat.gaussians.shading.sh9_basis)
vec3 sh9(vec3 n, vec3 c[9]) {
  float x = n.x, y = n.y, z = n.z;
  return ${SH9[0]} * c[0] + ${SH9[1]} * y * c[1] + ${SH9[1]} * z * c[2] + ${SH9[1]} * x * c[3]
       + ${SH9[2]} * x * y * c[4] + ${SH9[2]} * y * z * c[5] + ${SH9[3]} * (3.0 * z * z - 1.0) * c[6]
       + ${SH9[2]} * x * z * c[7] + ${SH9[4]} * (x * x - y * y) * c[8];
}
const vec4 CULLED = vec4(0.0, 0.0, 0.0, -1.0);
void main() {
  int g = here();
  oPos = vec4(0.0); oCol = vec4(0.0);
  if (g >= count) { oConic = CULLED; return; }
  uvec4 w0 = texelFetch(gTex, at(2 * g), 0), w1 = texelFetch(gTex, at(2 * g + 1), 0);
  vec2 uv = unpackHalf2x16(w0.y), dop = unpackHalf2x16(w0.z), rg = unpackHalf2x16(w0.w);
  vec4 qc = vec4(unpackHalf2x16(w1.x), unpackHalf2x16(w1.y));
  vec2 s01 = unpackHalf2x16(w1.z), s2b = unpackHalf2x16(w1.w);
  int k = int(w0.x);
  uvec4 fv = texelFetch(fTex, at(k), 0);
  ivec2 ia = at(int(fv.x)), ib = at(int(fv.y)), ic = at(int(fv.z));
  float u = uv.x, v = uv.y, w = 1.0 - u - v;
  // Phong point + d along the normalized interpolated normal (meshsplat.embedding)
  vec3 n = u * texelFetch(nTex, ia, 0).xyz + v * texelFetch(nTex, ib, 0).xyz + w * texelFetch(nTex, ic, 0).xyz;
  n *= inversesqrt(max(dot(n, n), 1e-24));
  vec3 surf = u * texelFetch(pTex, ia, 0).xyz + v * texelFetch(pTex, ib, 0).xyz + w * texelFetch(pTex, ic, 0).xyz;
  vec3 mean = surf + dop.x * n;
  // delta_q: blend of the corner quaternions sign-aligned to corner a; q = delta_q (x) q_canonical
  vec4 qa = texelFetch(qTex, ia, 0), qb = texelFetch(qTex, ib, 0), qq = texelFetch(qTex, ic, 0);
  vec4 dq = u * qa + (dot(qb, qa) < 0.0 ? -v : v) * qb + (dot(qq, qa) < 0.0 ? -w : w) * qq;
  dq /= max(length(dq), 1e-12);
  vec4 q = quatMul(dq, qc / max(length(qc), 1e-12));
  q /= max(length(q), 1e-12);
  float ratio = texelFetch(rTex, at(k), 0).x;
  float fac = scaleMode == 1 ? ratio : scaleMode == 2 ? sqrt(max(ratio, 0.0) + 1e-20) : 1.0;
  vec3 s = vec3(s01, s2b.x) * fac;
  vec3 mc = R * mean + tr;
  if (mc.z < ${NEAR_PLANE}) { oConic = CULLED; return; }
  // world covariance M M^T with M = rot(q) diag(s)  (columns of rot(q) scaled)
  mat3 Rq = quatMat(q);
  mat3 M = Rq * mat3(s.x, 0.0, 0.0, 0.0, s.y, 0.0, 0.0, 0.0, s.z);
  mat3 C = R * (M * transpose(M)) * transpose(R);
  // Jacobian at x/z, y/z clamped to the widened frustum (as gsplat / meshsplat.render.projection)
  float rz = 1.0 / mc.z;
  vec2 tanh_ = 0.5 * size / K.xy;
  vec2 limP = (size - K.zw) / K.xy + ${FOV_CLAMP_MARGIN} * tanh_;
  vec2 limN = K.zw / K.xy + ${FOV_CLAMP_MARGIN} * tanh_;
  vec2 txy = mc.z * clamp(mc.xy * rz, -limN, limP);
  // GLSL matrices are column-major: J = [[fx/z, 0, -fx tx/z^2], [0, fy/z, -fy ty/z^2]] as 3x3 (last row 0)
  mat3 J = mat3(K.x * rz, 0.0, 0.0,  0.0, K.y * rz, 0.0,  -K.x * txy.x * rz * rz, -K.y * txy.y * rz * rz, 0.0);
  mat3 c2 = J * C * transpose(J);
  float a0 = c2[0][0], b = c2[1][0], c0 = c2[1][1];
  float a = a0 + ${EPS2D}, c = c0 + ${EPS2D};
  float det = a * c - b * b;
  float op = dop.y;
  if (antialiased) op *= sqrt(clamp(det > 0.0 ? max(a0 * c0 - b * b, 0.0) / det : 1.0, 0.0, 1.0) + 1e-12);
  if (det <= 0.0 || op < ${ALPHA_THRESHOLD}) { oConic = CULLED; return; }
  float extend = min(${MAX_EXTEND}, sqrt(2.0 * log(op / ${ALPHA_THRESHOLD})));
  vec2 radius = ceil(extend * sqrt(vec2(a, c)));  // the rasterizer's box
  // the quad: the box, or, when smaller, the rectangle along the ellipse's axes around the same ellipse
  // {alpha >= 1/255} (half-axes extend sqrt(eigenvalue), a pixel of margin); either holds every pixel
  // the rasterizer draws (opacity <= 1: the box's extend is never capped), the fragment shader drops the rest
  float mid = 0.5 * (a + c), disc = sqrt(max(mid * mid - det, 0.0));
  vec2 h = extend * sqrt(vec2(mid + disc, max(mid - disc, 0.0))) + 1.0;
  vec2 e1 = abs(b) > 1e-6 * mid ? normalize(vec2(b, mid + disc - a)) : (a >= c ? vec2(1.0, 0.0) : vec2(0.0, 1.0));
  bool turned = h.x * h.y < radius.x * radius.y;
  oPos = vec4(K.xy * mc.xy * rz + K.zw, turned ? e1 * h.x : vec2(radius.x, 0.0));   // pixel position, y down
  oConic = vec4(vec3(c, -b, a) / det, turned ? h.y : radius.y);
  // colour, per frame: view-dependent SH (view direction in world or the triangle's canonical frame),
  // times the learned irradiance E(n) = max(0, sh9(n, irr)) of the posed normal (plus the key light
  // L V(x) max(0, n . w), its visibility V of the surface point before the offset d), plus the learned
  // specular sh9(n, spec), not clamped (meshsplat.gaussians.shading.Shading.shade)
  vec3 rgb = vec3(rg, s2b.y);
  if (shK > 0) {
    vec3 dir = mean + transpose(R) * tr;  // mean - camera centre
    if (shFrame == 1) dir = transpose(quatMat(dq)) * dir;
    rgb = viewColour(g, rgb, dir);
  }
  rgb = max(rgb, 0.0);
  if (shadeNormal > 0) {
    vec3 sn = n;
    if (shadeNormal == 2) {             // shortest posed axis (first minimum), facing the Phong normal's side
      int i = s.y < s.x ? (s.z < s.y ? 2 : 1) : (s.z < s.x ? 2 : 0);
      sn = Rq[i];
      if (dot(sn, n) < 0.0) sn = -sn;
    }
    vec3 e = max(sh9(sn, irr), 0.0);
    if (keyOn) e += keyLight * (keyVisible(surf, n) * max(dot(sn, keyDir), 0.0));
    rgb *= e;
    if (specular) rgb += sh9(sn, spec);
  }
  oCol = vec4(rgb, op);
}`;

// the draw: one quad (two indexed triangles over four vertices, no vertex attributes) per Gaussian in
// back-to-front order around its pass-C position; one plain draw call, not an instanced one (SwiftShader, the
// software WebGL, pays a draw call's set-up per instance: 44 us a Gaussian)
const VERT = `#version 300 es
precision highp float; precision highp int; precision highp sampler2D; precision highp usampler2D;
uniform usampler2D orderTex;            // slot -> Gaussian index, back to front (the sort's order)
uniform sampler2D posTex, conicTex, colTex;  // pass C's outputs
uniform vec2 size;                      // width, height (pixels)
out vec2 offs; out vec3 conic; out vec4 col;
const vec2 CORNERS[4] = vec2[4](vec2(-1.0, -1.0), vec2(1.0, -1.0), vec2(-1.0, 1.0), vec2(1.0, 1.0));
ivec2 at(int i) { return ivec2(i & ${TEX_WIDTH - 1}, i >> ${Math.log2(TEX_WIDTH)}); }
void main() {
  int g = int(texelFetch(orderTex, at(gl_VertexID >> 2), 0).x);
  vec2 corner = CORNERS[gl_VertexID & 3];
  vec4 cn = texelFetch(conicTex, at(g), 0);
  if (cn.w < 0.0) { gl_Position = vec4(0.0, 0.0, 2.0, 1.0); return; }
  vec4 pr = texelFetch(posTex, at(g), 0);
  vec2 u = pr.zw, v = vec2(-u.y, u.x) * (cn.w / max(length(u), 1e-30));  // the quad's half-axes
  offs = corner.x * u + corner.y * v;
  vec2 px = pr.xy + offs;
  gl_Position = vec4(2.0 * px.x / size.x - 1.0, 1.0 - 2.0 * px.y / size.y, 0.0, 1.0);
  conic = cn.xyz;
  col = texelFetch(colTex, at(g), 0);
}`;

const FRAG = `#version 300 es
precision highp float;
in vec2 offs; in vec3 conic; in vec4 col;
out vec4 frag;
void main() {
  float power = -0.5 * (conic.x * offs.x * offs.x + conic.z * offs.y * offs.y) - conic.y * offs.x * offs.y;
  if (power > 0.0) discard;
  float alpha = min(${ALPHA_MAX}, col.a * exp(power));
  if (alpha < ${ALPHA_THRESHOLD}) discard;
  frag = vec4(col.rgb * alpha, alpha);  // premultiplied, blended ONE, ONE_MINUS_SRC_ALPHA back to front
}`;

// the last pass: the splats' float image (RGBA16F, blended unclamped as the rasterizer accumulates) to the
// canvas, clamped to [0, 1] once (as the rasterizer clamps only the blended image); opaque, as the 8-bit path
const COMPOSITE_FRAG = `#version 300 es
precision highp float; precision highp sampler2D;
uniform sampler2D img;
out vec4 frag;
void main() { frag = vec4(clamp(texelFetch(img, ivec2(gl_FragCoord.xy), 0).rgb, 0.0, 1.0), 1.0); }`;

function compile(gl, type, src) {
  const s = gl.createShader(type);
  gl.shaderSource(s, src);
  gl.compileShader(s);
  if (!gl.getShaderParameter(s, gl.COMPILE_STATUS)) throw new Error(gl.getShaderInfoLog(s));
  return s;
}

function program(gl, vs, fs, uniforms) {
  const prog = gl.createProgram();
  gl.attachShader(prog, compile(gl, gl.VERTEX_SHADER, vs));
  gl.attachShader(prog, compile(gl, gl.FRAGMENT_SHADER, fs));
  gl.linkProgram(prog);
  if (!gl.getProgramParameter(prog, gl.LINK_STATUS)) throw new Error(gl.getProgramInfoLog(prog));
  return { prog, loc: Object.fromEntries(uniforms.map((n) => [n, gl.getUniformLocation(prog, n)])) };
}

const FORMATS = { f4: ["RGBA32F", "RGBA", "FLOAT", 4, Float32Array], u4: ["RGBA32UI", "RGBA_INTEGER", "UNSIGNED_INT", 4, Uint32Array],
                  f1: ["R32F", "RED", "FLOAT", 1, Float32Array], u1: ["R32UI", "RED_INTEGER", "UNSIGNED_INT", 1, Uint32Array] };

/** A TEX_WIDTH-wide data texture of `n` texels; `data` (optional) is copied in, zero-padded to whole rows. */
function dataTexture(gl, kind, n, data) {
  const [internal, format, type, ch, T] = FORMATS[kind];
  const texels = texSize(n);
  let buf = null;
  if (data) { buf = new T(texels * ch); buf.set(data.subarray ? data.subarray(0, Math.min(data.length, texels * ch)) : data); }
  const tex = gl.createTexture();
  gl.bindTexture(gl.TEXTURE_2D, tex);
  for (const p of [gl.TEXTURE_MIN_FILTER, gl.TEXTURE_MAG_FILTER]) gl.texParameteri(gl.TEXTURE_2D, p, gl.NEAREST);
  gl.texImage2D(gl.TEXTURE_2D, 0, gl[internal], TEX_WIDTH, texels / TEX_WIDTH, 0, gl[format], gl[type], buf);
  return { tex, kind, rows: texels / TEX_WIDTH, ch, T, texels };
}

function updateTexture(gl, t, data) {
  const [, format, type] = FORMATS[t.kind];
  let buf = data;
  if (data.length !== t.texels * t.ch) { buf = new t.T(t.texels * t.ch); buf.set(data); }
  gl.bindTexture(gl.TEXTURE_2D, t.tex);
  gl.texSubImage2D(gl.TEXTURE_2D, 0, 0, 0, TEX_WIDTH, t.rows, gl[format], gl[type], buf);
}

/** Vertex -> incident faces (with repeats for repeated corners), faces increasing: {va [V*4], adj [3F]}. */
export function vertexFaces(faces, V) {
  const count = new Uint32Array(V);
  for (let i = 0; i < faces.length; i++) count[faces[i]]++;
  const va = new Uint32Array(4 * V), fill = new Uint32Array(V);
  let start = 0;
  for (let v = 0; v < V; v++) { va[4 * v] = start; va[4 * v + 1] = count[v]; start += count[v]; }
  const adj = new Uint32Array(faces.length);
  for (let i = 0; i < faces.length; i++) { const v = faces[i]; adj[va[4 * v] + fill[v]++] = Math.floor(i / 3); }
  return { va, adj };
}

/**
 * The part of bundle `b`'s mesh that the GPU posing passes need: the faces that carry Gaussians, every face
 * around their corners (a corner's normal and frame sum over all of its faces), and those faces' vertices,
 * renumbered in their bundle order, so each corner sums the same faces in the same order as over the whole
 * mesh (the same bits). A head's Gaussians lie on a fifth of its faces (none on the back of the head, inside
 * the mouth or on the eyeballs); the posing passes shrink with it. Returns { V, F, faces [F*3] (its vertex
 * numbers), vertex [V] (its vertex -> the bundle's), face [F] (its face -> the bundle's), gaussianFace [N]
 * (each Gaussian's face, its number) }; vertex and face are null where it is the whole mesh.
 */
export function drawMesh(b) {
  const V = b.V, F = b.F, faces = b.faces, corner = new Uint8Array(V), carries = new Uint8Array(F);
  for (let g = 0; g < b.N; g++) carries[b.face[g]] = 1;
  for (let k = 0; k < F; k++) if (carries[k]) for (let j = 0; j < 3; j++) corner[faces[3 * k + j]] = 1;
  const faceNo = new Int32Array(F).fill(-1), vertNo = new Int32Array(V).fill(-1);
  let nF = 0, nV = 0;
  for (let k = 0; k < F; k++) {
    if (corner[faces[3 * k]] || corner[faces[3 * k + 1]] || corner[faces[3 * k + 2]]) {
      faceNo[k] = nF++;
      for (let j = 0; j < 3; j++) vertNo[faces[3 * k + j]] = 0;
    }
  }
  for (let v = 0; v < V; v++) if (vertNo[v] === 0) vertNo[v] = nV++;
  if (b.N === 0 || (nF === F && nV === V)) return wholeMesh(b);
  const vertex = new Uint32Array(nV), face = new Uint32Array(nF), out = new Uint32Array(3 * nF), gaussianFace = new Uint32Array(b.N);
  for (let v = 0; v < V; v++) if (vertNo[v] >= 0) vertex[vertNo[v]] = v;
  for (let k = 0; k < F; k++) {
    const i = faceNo[k];
    if (i < 0) continue;
    face[i] = k;
    for (let j = 0; j < 3; j++) out[3 * i + j] = vertNo[faces[3 * k + j]];
  }
  for (let g = 0; g < b.N; g++) gaussianFace[g] = faceNo[b.face[g]];
  return { V: nV, F: nF, faces: out, vertex, face, gaussianFace };
}

/** drawMesh's answer for the whole mesh of bundle `b` (every face posed, nothing renumbered). */
function wholeMesh(b) {
  return { V: b.V, F: b.F, faces: b.faces, vertex: null, face: null, gaussianFace: b.face };
}

/** Rows `rows` (an index array, or null: all) of `src`, each `width` values wide, as a new array of its type. */
function gatherRows(src, width, rows) {
  if (rows === null) return src;
  const out = new src.constructor(rows.length * width);
  for (let i = 0; i < rows.length; i++) for (let j = 0, o = rows[i] * width; j < width; j++) out[i * width + j] = src[o + j];
  return out;
}

/**
 * Splat renderer on a WebGL2 canvas. Static textures: packed Gaussians (and their SH bands), faces, canonical face
 * frames, vertex->face adjacency (and the rig). Per pose: `setVertices(p)` (vertex frames) or
 * `setRig(state)` (live glTF), then the face and vertex passes run on the GPU, over drawMesh(b) (the faces
 * near the Gaussians); per sort:
 * `setOrder(order, n)`; `draw(viewmat, K, background)` runs pass C (each Gaussian projected and shaded once,
 * into three data textures), then issues one draw call of their quads into an RGBA16F target
 * (`floatTarget`; else straight into the canvas) and one full-screen pass that clamps it into the canvas.
 */
export class SplatRenderer {
  constructor(canvas, b, { floatTarget = true, allFaces = false } = {}) {
    const gl = canvas.getContext("webgl2", { antialias: false, premultipliedAlpha: false, preserveDrawingBuffer: true });
    if (!gl) throw new Error("WebGL2 is not available in this browser");
    if (!gl.getExtension("EXT_color_buffer_float")) throw new Error("this browser cannot render to float textures (EXT_color_buffer_float)");
    this.gl = gl; this.b = b;
    const m = this.mesh = allFaces ? wholeMesh(b) : drawMesh(b); // allFaces: ?mesh=all, for comparisons
    const maxRows = gl.getParameter(gl.MAX_TEXTURE_SIZE);
    if (texSize(2 * b.N) / TEX_WIDTH > maxRows) throw new Error(`${b.N} Gaussians exceed this GPU's texture size`);
    this.prep = program(gl, PASS_VERT, PREP_FRAG, ["count", "R", "tr", "K", "size", "gTex", "shTex", "fTex", "pTex", "nTex", "qTex", "rTex",
      "scaleMode", "shK", "shTexels", "shFrame", "shadeNormal", "irr", "specular", "spec", "antialiased",
      "keyOn", "keyLight", "keyDir", "keyA", "keyB", "keyW", "keyMaps", "keyCentre", "keyRadius", "keyCell", "keyGrid", "kTex"]);
    this.splat = program(gl, VERT, FRAG, ["orderTex", "posTex", "conicTex", "colTex", "size"]);
    this.facePass = program(gl, PASS_VERT, FACE_FRAG, ["count", "pTex", "cfTex", "fTex"]);
    this.vertPass = program(gl, PASS_VERT, VERTEX_FRAG, ["count", "fqTex", "fcTex", "adjTex", "vaTex"]);
    // the splats blend into an RGBA16F target (renderable and blendable with EXT_color_buffer_float),
    // then one full-screen pass clamps it to the canvas; without a complete float target (or with
    // floatTarget false: ?float=0), they blend straight into the canvas's 8-bit buffer, which clamps
    // every splat's premultiplied colour at 1 (darker where bright splats overlap)
    this.composite = program(gl, PASS_VERT, COMPOSITE_FRAG, ["img"]);
    this.target = null;
    this.blend8 = false; // this draw through the 8-bit path even with a float target (webcam mode on slow draws)
    this.floatTarget = floatTarget && this.resizeTarget(1, 1);
    if (floatTarget && !this.floatTarget) console.warn("meshsplat viewer: no RGBA16F render target; blending in 8 bits (colours above 1 clamped per splat)");
    const ftex = new Uint32Array(4 * m.F);
    for (let k = 0; k < m.F; k++) for (let j = 0; j < 3; j++) ftex[4 * k + j] = m.faces[3 * k + j];
    const cf = new Float32Array(12 * m.F); // rows (t_i, b_i, n_i, area) of the canonical face frames
    for (let k = 0; k < m.F; k++) {
      const o = m.face ? m.face[k] : k;
      for (let i = 0; i < 3; i++) for (let j = 0; j < 3; j++) cf[12 * k + 4 * i + j] = b.canoFrames[9 * o + 3 * i + j];
      cf[12 * k + 3] = b.canoAreas[o];
    }
    const { va, adj } = vertexFaces(m.faces, m.V);
    let packed = b.packed;
    if (m.face) { // each Gaussian's face word (bundle.py pack_gaussians: word 0 of 8) in the draw mesh's numbers
      packed = Uint32Array.from(b.packed);
      for (let g = 0; g < b.N; g++) packed[8 * g] = m.gaussianFace[g];
    }
    this.t = {
      g: dataTexture(gl, "u4", 2 * b.N, packed), f: dataTexture(gl, "u4", m.F, ftex),
      sh: b.shRest ? dataTexture(gl, "u4", b.shRest.length / 4, b.shRest) : dataTexture(gl, "u4", 1),
      cf: dataTexture(gl, "f4", 3 * m.F, cf), va: dataTexture(gl, "u4", m.V, va), adj: dataTexture(gl, "u1", adj.length, adj),
      p: dataTexture(gl, "f4", m.V), n: dataTexture(gl, "f4", m.V), q: dataTexture(gl, "f4", m.V),
      fq: dataTexture(gl, "f4", m.F), fc: dataTexture(gl, "f4", m.F), r: dataTexture(gl, "f4", m.F),
      gPos: dataTexture(gl, "f4", b.N), gConic: dataTexture(gl, "f4", b.N), gCol: dataTexture(gl, "f4", b.N),
      order: dataTexture(gl, "u1", b.N),
    };
    // the key light's height maps (model.occlusion=key): S grid x grid, stacked, rebuilt on the CPU per pose (setKeyMap)
    this.key = (b.header.shading && b.header.shading.key) || null;
    this.keyMs = 0;
    const kg = this.key ? this.key.grid : 1, ks = this.key ? keyShadowDirections(this.key).length : 1;
    if (ks > KEY_MAX_MAPS) throw new Error(`the key light's shadow averages ${ks} height maps; this player shades at most ${KEY_MAX_MAPS}`);
    if (kg * ks > maxRows) throw new Error(`the key light's ${ks} height maps of ${kg}^2 cells exceed this GPU's texture size`);
    this.t.k = { tex: gl.createTexture(), grid: kg, maps: ks };
    if (this.key) this.keyFrames = { grid: kg, frame: keyFrame(this.key.direction), frames: keyShadowDirections(this.key).map(keyFrame) };
    gl.bindTexture(gl.TEXTURE_2D, this.t.k.tex);
    for (const p of [gl.TEXTURE_MIN_FILTER, gl.TEXTURE_MAG_FILTER]) gl.texParameteri(gl.TEXTURE_2D, p, gl.NEAREST);
    gl.texImage2D(gl.TEXTURE_2D, 0, gl.R32F, kg, ks * kg, 0, gl.RED, gl.FLOAT, new Float32Array(ks * kg * kg));
    if (b.rig) {
      const r = b.rig, base4 = new Float32Array(4 * m.V), delta4 = new Float32Array(4 * Math.max(1, r.deltas.length / 3));
      for (let v = 0; v < m.V; v++) for (let j = 0, o = m.vertex ? m.vertex[v] : v; j < 3; j++) base4[4 * v + j] = r.base[3 * o + j];
      for (let i = 0; i < r.deltas.length / 3; i++) {
        for (let j = 0; j < 3; j++) delta4[4 * i + j] = r.deltas[3 * i + j];
        if (r.deltaTarget) delta4[4 * i + 3] = r.deltaTarget[i];
      }
      if (!r.deltaTarget) { // dense groups: vertex v's m-th delta is target m
        const info = r.morphInfo;
        for (let v = 0; v < b.V; v++) for (let k = 0; k < info[4 * v + 1]; k++) delta4[4 * (info[4 * v] + k * info[4 * v + 2]) + 3] = k;
      }
      this.skinPass = program(gl, PASS_VERT, SKIN_FRAG, ["count", "K", "baseTex", "deltaTex", "weightTex", "pairTex", "jwTex", "morphTex", "jiTex"]);
      Object.assign(this.t, { // per vertex of the draw mesh: its morph rows and joint pairs (the deltas stay whole)
        base: dataTexture(gl, "f4", m.V, base4), delta: dataTexture(gl, "f4", delta4.length / 4, delta4),
        morph: dataTexture(gl, "u4", m.V, gatherRows(r.morphInfo, 4, m.vertex)),
        ji: dataTexture(gl, "u4", m.V * r.K / 4, gatherRows(r.pairIndex, r.K, m.vertex)),
        jw: dataTexture(gl, "f4", m.V * r.K / 4, gatherRows(r.pairWeight, r.K, m.vertex)), pair: dataTexture(gl, "f4", 3 * r.P),
        weight: dataTexture(gl, "f1", Math.max(1, r.defaultWeights.length)),
      });
      this.fbSkin = this.framebuffer([this.t.p]);
    }
    this.fbFace = this.framebuffer([this.t.fq, this.t.fc, this.t.r]);
    this.fbVert = this.framebuffer([this.t.n, this.t.q]);
    this.fbPrep = this.framebuffer([this.t.gPos, this.t.gConic, this.t.gCol]);
    this.vao = gl.createVertexArray();
    gl.bindVertexArray(this.vao);
    const quad = gl.createBuffer();
    gl.bindBuffer(gl.ARRAY_BUFFER, quad);
    gl.bufferData(gl.ARRAY_BUFFER, new Float32Array([-1, -1, 1, -1, -1, 1, 1, 1]), gl.STATIC_DRAW);
    gl.enableVertexAttribArray(0);
    gl.vertexAttribPointer(0, 2, gl.FLOAT, false, 0, 0);
    // the splat draw reads no vertex attributes: vertex 4 s + c is corner c of slot s's quad, two triangles
    // each (indexed, so that each corner is shaded once)
    this.splatVao = gl.createVertexArray();
    gl.bindVertexArray(this.splatVao);
    const quads = new Uint32Array(6 * b.N);
    for (let s = 0, o = 0, v = 0; s < b.N; s++, o += 6, v += 4) {
      quads[o] = v; quads[o + 1] = v + 1; quads[o + 2] = v + 2; quads[o + 3] = v + 2; quads[o + 4] = v + 1; quads[o + 5] = v + 3;
    }
    gl.bindBuffer(gl.ELEMENT_ARRAY_BUFFER, gl.createBuffer());
    gl.bufferData(gl.ELEMENT_ARRAY_BUFFER, quads, gl.STATIC_DRAW);
    gl.bindVertexArray(null);
    this.visible = 0;
  }

  framebuffer(targets) {
    const gl = this.gl, fb = gl.createFramebuffer();
    gl.bindFramebuffer(gl.FRAMEBUFFER, fb);
    targets.forEach((t, i) => gl.framebufferTexture2D(gl.FRAMEBUFFER, gl.COLOR_ATTACHMENT0 + i, gl.TEXTURE_2D, t.tex, 0));
    gl.drawBuffers(targets.map((_, i) => gl.COLOR_ATTACHMENT0 + i));
    const status = gl.checkFramebufferStatus(gl.FRAMEBUFFER);
    gl.bindFramebuffer(gl.FRAMEBUFFER, null);
    if (status !== gl.FRAMEBUFFER_COMPLETE) throw new Error(`float render target incomplete (${status})`);
    return { fb, rows: targets[0].rows };
  }

  /** The float target at `w` x `h` (re-allocated when the canvas size changed); false if incomplete. */
  resizeTarget(w, h) {
    const gl = this.gl;
    if (this.target && this.target.w === w && this.target.h === h) return true;
    const t = this.target || { tex: gl.createTexture(), fb: gl.createFramebuffer() };
    gl.bindTexture(gl.TEXTURE_2D, t.tex);
    for (const p of [gl.TEXTURE_MIN_FILTER, gl.TEXTURE_MAG_FILTER]) gl.texParameteri(gl.TEXTURE_2D, p, gl.NEAREST);
    gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGBA16F, w, h, 0, gl.RGBA, gl.HALF_FLOAT, null);
    gl.bindFramebuffer(gl.FRAMEBUFFER, t.fb);
    gl.framebufferTexture2D(gl.FRAMEBUFFER, gl.COLOR_ATTACHMENT0, gl.TEXTURE_2D, t.tex, 0);
    gl.drawBuffers([gl.COLOR_ATTACHMENT0]);
    const ok = gl.checkFramebufferStatus(gl.FRAMEBUFFER) === gl.FRAMEBUFFER_COMPLETE;
    gl.bindFramebuffer(gl.FRAMEBUFFER, null);
    Object.assign(t, { w, h });
    this.target = t;
    return ok;
  }

  bind(p, textures) { // textures: {uniformName: texture}
    const gl = this.gl;
    Object.entries(textures).forEach(([name, t], i) => {
      gl.activeTexture(gl.TEXTURE0 + i);
      gl.bindTexture(gl.TEXTURE_2D, t.tex);
      gl.uniform1i(p.loc[name], i);
    });
  }

  runPass(p, fb, count, textures, extra) {
    const gl = this.gl;
    gl.bindFramebuffer(gl.FRAMEBUFFER, fb.fb);
    gl.viewport(0, 0, TEX_WIDTH, fb.rows);
    gl.disable(gl.BLEND);
    gl.useProgram(p.prog);
    gl.uniform1i(p.loc.count, count);
    if (extra) extra(p.loc);
    this.bind(p, textures);
    gl.bindVertexArray(this.vao);
    gl.drawArrays(gl.TRIANGLE_STRIP, 0, 4);
    gl.bindVertexArray(null);
    gl.bindFramebuffer(gl.FRAMEBUFFER, null);
  }

  /** Posed vertex positions [V*3] (vertex-frame driver): upload, then the face and vertex passes. */
  setVertices(p) {
    const m = this.mesh, V = m.V, p4 = this.p4 || (this.p4 = new Float32Array(4 * V));
    for (let v = 0; v < V; v++) {
      const o = 3 * (m.vertex ? m.vertex[v] : v);
      p4[4 * v] = p[o]; p4[4 * v + 1] = p[o + 1]; p4[4 * v + 2] = p[o + 2];
    }
    updateTexture(this.gl, this.t.p, p4);
    this.poseMeshPasses();
  }

  /** The key light's height maps of a pose (a shadowJob result: its depths [maps * grid * grid] and
   * grid placement), uploaded; the splat shader reads them from the next draw on. */
  setKeyMaps(r) {
    const gl = this.gl, k = this.t.k;
    gl.bindTexture(gl.TEXTURE_2D, k.tex);
    gl.texSubImage2D(gl.TEXTURE_2D, 0, 0, 0, k.grid, k.maps * k.grid, gl.RED, gl.FLOAT, r.depth);
    this.keyMap = { ...this.keyFrames, centre: r.centre, radius: r.radius, cell: r.cell };
    this.keyMs = r.ms;
  }

  /** Rig state of evalRig (live glTF driver): skinning pass, then the face and vertex passes. */
  setRig(state) {
    const gl = this.gl, t = this.t, P = this.b.rig.P, pairs = this.pair4 || (this.pair4 = new Float32Array(12 * P));
    pairs.set(state.pairs);
    updateTexture(gl, t.pair, pairs);
    if (state.weights.length) updateTexture(gl, t.weight, state.weights);
    this.runPass(this.skinPass, this.fbSkin, this.mesh.V, { baseTex: t.base, deltaTex: t.delta, weightTex: t.weight,
      pairTex: t.pair, jwTex: t.jw, morphTex: t.morph, jiTex: t.ji }, (loc) => gl.uniform1i(loc.K, this.b.rig.K));
    this.poseMeshPasses();
  }

  poseMeshPasses() {
    const t = this.t;
    this.runPass(this.facePass, this.fbFace, this.mesh.F, { pTex: t.p, cfTex: t.cf, fTex: t.f });
    this.runPass(this.vertPass, this.fbVert, this.mesh.V, { fqTex: t.fq, fcTex: t.fc, adjTex: t.adj, vaTex: t.va });
  }

  /** The sort's back-to-front Gaussian indices `order[0:n]`, uploaded in whole texture rows. */
  setOrder(order, n) {
    const gl = this.gl, t = this.t.order, rows = Math.ceil(n / TEX_WIDTH);
    if (rows > 0) {
      const buf = this.orderRows || (this.orderRows = new Uint32Array(t.texels));
      buf.set(order.subarray(0, n));
      gl.bindTexture(gl.TEXTURE_2D, t.tex);
      gl.texSubImage2D(gl.TEXTURE_2D, 0, 0, 0, TEX_WIDTH, rows, gl.RED_INTEGER, gl.UNSIGNED_INT, buf.subarray(0, rows * TEX_WIDTH));
    }
    this.visible = n;
  }

  draw(viewmat, K, background) {
    const gl = this.gl, w = gl.canvas.width, h = gl.canvas.height, t = this.t;
    if (this.floatTarget && !this.blend8 && !this.resizeTarget(Math.max(w, 1), Math.max(h, 1))) {
      this.floatTarget = false;
      console.warn(`meshsplat viewer: no ${w}x${h} RGBA16F render target; blending in 8 bits from now on`);
    }
    const float = this.floatTarget && !this.blend8;
    if (this.visible > 0) this.runPass(this.prep, this.fbPrep, this.b.N, { gTex: t.g, shTex: t.sh, fTex: t.f, pTex: t.p,
      nTex: t.n, qTex: t.q, rTex: t.r, kTex: t.k }, (loc) => this.prepUniforms(loc, viewmat, K, w, h));
    gl.bindFramebuffer(gl.FRAMEBUFFER, float ? this.target.fb : null);
    gl.viewport(0, 0, w, h);
    gl.clearColor(background[0], background[1], background[2], 1);
    gl.clear(gl.COLOR_BUFFER_BIT);
    const p = this.splat;
    gl.useProgram(p.prog);
    gl.disable(gl.DEPTH_TEST);
    gl.enable(gl.BLEND);
    gl.blendFunc(gl.ONE, gl.ONE_MINUS_SRC_ALPHA);
    gl.uniform2f(p.loc.size, w, h);
    this.bind(p, { orderTex: t.order, posTex: t.gPos, conicTex: t.gConic, colTex: t.gCol });
    gl.bindVertexArray(this.splatVao);
    if (this.visible > 0) gl.drawElements(gl.TRIANGLES, 6 * this.visible, gl.UNSIGNED_INT, 0);
    gl.bindVertexArray(this.vao);
    if (float) { // one full-screen pass: clamp the blended image into the canvas
      gl.bindFramebuffer(gl.FRAMEBUFFER, null);
      gl.disable(gl.BLEND);
      gl.useProgram(this.composite.prog);
      this.bind(this.composite, { img: this.target });
      gl.drawArrays(gl.TRIANGLE_STRIP, 0, 4);
    }
    gl.bindVertexArray(null);
  }

  /** Pass C's uniforms: the view, the canvas size `w` x `h`, the SH and shading of the header, the key light. */
  prepUniforms(loc, viewmat, K, w, h) {
    const gl = this.gl, m = viewmat; // row-major -> GLSL column-major: pass transpose=false with columns
    gl.uniformMatrix3fv(loc.R, false, [m[0], m[4], m[8], m[1], m[5], m[9], m[2], m[6], m[10]]);
    gl.uniform3f(loc.tr, m[3], m[7], m[11]);
    gl.uniform4f(loc.K, K[0], K[1], K[2], K[3]);
    gl.uniform2f(loc.size, w, h);
    const hd = this.b.header, shK = [0, 3, 8, 15][hd.sh_degree || 0], shade = hd.shading;
    gl.uniform1i(loc.scaleMode, { none: 0, area: 1, sqrt_area: 2 }[hd.scale_mode]);
    gl.uniform1i(loc.shK, shK);
    gl.uniform1i(loc.shTexels, shK ? this.b.shRest.length / (4 * this.b.N) : 0);
    gl.uniform1i(loc.shFrame, hd.sh_frame === "triangle" ? 1 : 0);
    gl.uniform1i(loc.shadeNormal, shade ? (shade.normal === "axis" ? 2 : 1) : 0);
    if (shade) gl.uniform3fv(loc.irr, shade.coeffs.flat());
    gl.uniform1i(loc.specular, shade && shade.specular ? 1 : 0);
    if (shade && shade.specular) gl.uniform3fv(loc.spec, shade.specular.flat());
    gl.uniform1i(loc.antialiased, hd.antialiased ? 1 : 0);
    const key = shade && this.key && this.keyMap ? this.keyMap : null;
    gl.uniform1i(loc.keyOn, key ? 1 : 0);
    if (key) {
      gl.uniform3fv(loc.keyLight, this.key.light); gl.uniform3fv(loc.keyDir, key.frame.w);
      for (const [name, axis] of [["keyA", "a"], ["keyB", "b"], ["keyW", "w"]]) gl.uniform3fv(loc[name], key.frames.flatMap((f) => f[axis]));
      gl.uniform1i(loc.keyMaps, key.frames.length); gl.uniform3fv(loc.keyCentre, key.centre);
      gl.uniform1f(loc.keyRadius, key.radius); gl.uniform1f(loc.keyCell, key.cell); gl.uniform1i(loc.keyGrid, key.grid);
    }
  }
}

// ------------------------------------------------------------------ per-frame driver (main thread)
/**
 * The main thread's per-frame work without WebGL: vertex frames -> decode the frame's vertices
 * (per vertex); live glTF -> evaluate the clip (per node and joint) and the morph weights.
 * Shared by the page and bench/viewer.py.
 */
export class FramePoser {
  constructor(b) {
    this.b = b; this.p = new Float64Array(3 * b.V); this.verts32 = new Float32Array(3 * b.V); this.rigState = undefined;
  }

  /** {verts} of vertex frame `t`. */
  frame(t) {
    this.p = frameVertices(this.b, t, this.p);
    this.verts32.set(this.p);
    return { verts: this.verts32 };
  }

  /** {rig} of clip index `clip` at `time` s with morph weight overrides (NaN = from the clip). */
  rig(clip, time, override, pose) {
    this.rigState = evalRig(this.b.rig, clip, time, override, this.rigState, pose);
    return { rig: this.rigState };
  }
}

// ------------------------------------------------------------------ webcam: face landmarks -> ARKit weights and head pose
// The page's webcam mode (docs/viewer.md): MediaPipe's 478 face landmarks of a frame (pixels) -> the
// expression weights and head pose of the ICT head the tracker fits (meshsplat.track.head_fit), with
// the identity at the ICT neutral and the gaze at rest. The model is the head's blend-shape basis
// restricted to the landmarks (meshsplat.viewer.webcam.webcam_model): point_l(w) = neutral_l +
// sum_e w_e delta_e,l, posed as R (point - pivot) + pivot + t, seen by a camera at the origin looking
// along -z (world +y up: OpenCV axes are (x, -y, -z)) with focal length from a 60° diagonal field of view.
// Loss, as fit_head's per-frame terms: sum of Huber(3) of the reprojection residuals in units of 1/100
// of the landmarks' spread, + 0.5 sum w (w in [0, 1]), + `smooth` x (30 |w - w'|² + 100 |rot - rot'|² +
// 0.3 |t - t'|²) towards the previous frame's solution. Gauss-Newton (Levenberg-Marquardt damped,
// iteratively reweighted for the Huber loss) with an active set for the bounds.

/** Landmark model of a bundle's `header.webcam` and its sections. */
export function decodeWebcam(h, arr) {
  const L = h.landmarks, E = h.names.length, deltas = Float64Array.from(arr.webcam_deltas);
  const deltasByLandmark = new Float64Array(deltas.length); // [L][E][3]: a landmark's deltas side by side (solveFace's rows)
  for (let l = 0; l < L; l++) for (let e = 0; e < E; e++) for (let k = 0; k < 3; k++) deltasByLandmark[(l * E + e) * 3 + k] = deltas[(e * L + l) * 3 + k];
  return { L, E, names: h.names, used: Uint32Array.from(h.used), usedMax: Math.max(-1, ...h.used), pivot: Float64Array.from(h.pivot),
           headSize: h.head_size_cm || null,
           fovDiag: h.diagonal_fov_deg, neutral: Float64Array.from(arr.webcam_neutral),
           deltas, deltasByLandmark, landmarker: h.landmarker };
}

/** The diagonal of the bounding box of points [N*3]. */
export function boxDiagonal(p) {
  const lo = [Infinity, Infinity, Infinity], hi = [-Infinity, -Infinity, -Infinity];
  for (let i = 0; i < p.length; i += 3) for (let k = 0; k < 3; k++) { lo[k] = Math.min(lo[k], p[i + k]); hi[k] = Math.max(hi[k], p[i + k]); }
  return Math.hypot(hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2]);
}

/** Row-major 3x3 rotation of axis-angle `a` (Rodrigues). */
export function axisAngleMatrix(a) {
  const th = Math.hypot(a[0], a[1], a[2]);
  if (th < 1e-12) return [1, -a[2], a[1], a[2], 1, -a[0], -a[1], a[0], 1];
  const x = a[0] / th, y = a[1] / th, z = a[2] / th, c = Math.cos(th), s = Math.sin(th), C = 1 - c;
  return [c + x * x * C, x * y * C - z * s, x * z * C + y * s,
          y * x * C + z * s, c + y * y * C, y * z * C - x * s,
          z * x * C - y * s, z * y * C + x * s, c + z * z * C];
}

/** Axis-angle [3] of a row-major 3x3 rotation. */
export function matrixAxisAngle(R) {
  const c = Math.max(-1, Math.min(1, (R[0] + R[4] + R[8] - 1) / 2)), th = Math.acos(c);
  const v = [R[7] - R[5], R[2] - R[6], R[3] - R[1]];
  if (th < 1e-6) return [v[0] / 2, v[1] / 2, v[2] / 2];
  if (Math.PI - th < 1e-4) { // near a half turn: the axis from the symmetric part
    const d = [R[0], R[4], R[8]], k = d.indexOf(Math.max(...d));
    const ax = [0, 0, 0];
    ax[k] = Math.sqrt(Math.max((d[k] + 1) / 2, 0));
    for (let j = 0; j < 3; j++) if (j !== k) ax[j] = (R[3 * k + j] + R[3 * j + k]) / (4 * ax[k]);
    return ax.map((x) => x * th);
  }
  const s = th / (2 * Math.sin(th));
  return [v[0] * s, v[1] * s, v[2] * s];
}

function mat3Mul(A, B) {
  const o = new Array(9);
  for (let i = 0; i < 3; i++) for (let j = 0; j < 3; j++) o[3 * i + j] = A[3 * i] * B[j] + A[3 * i + 1] * B[3 + j] + A[3 * i + 2] * B[6 + j];
  return o;
}

/** Focal length (pixels) of a `width` x `height` frame with the model's diagonal field of view (head_fit.focal_from_fov). */
export function webcamFocal(m, width, height) { return 0.5 * Math.hypot(width, height) / Math.tan(m.fovDiag * Math.PI / 360); }

/**
 * Solve one frame. `obs`: [L*2] landmark pixels (x right, y down, in a `width` x `height` frame), or
 * fewer (the landmarker's 468 points without the 10 iris points: `m.used` must lie among them);
 * `prev`: the previous frame's result (warm start and temporal prior) or null. Options: `smooth`
 * (temporal prior weight, 0 = none), `iterations`, `focal` (pixels). Returns
 * { R [9] row-major, rot [3] axis-angle, t [3], w Float64Array [E] in [0, 1], cost, iterations, errorPx }.
 */
export function solveFace(m, obs, width, height, prev = null, opts = {}) {
  const L = m.L, E = m.E, U = m.used, n = 6 + E, f = opts.focal || webcamFocal(m, width, height);
  const cx = width / 2, cy = height / 2, smooth = opts.smooth || 0, delta = 3;
  const Lo = Math.min(L, obs.length >> 1); // the landmarks given (all L, or the first 468)
  for (let k = 0; k < U.length; k++) if (U[k] >= Lo) throw new Error(`solveFace: landmark ${U[k]} is used but only ${Lo} are given`);
  // residual unit: 1/100 of the given landmarks' RMS spread in the image
  let mx = 0, my = 0;
  for (let l = 0; l < Lo; l++) { mx += obs[2 * l]; my += obs[2 * l + 1]; }
  mx /= Lo; my /= Lo;
  let s2 = 0;
  for (let l = 0; l < Lo; l++) s2 += (obs[2 * l] - mx) ** 2 + (obs[2 * l + 1] - my) ** 2;
  const spread2d = Math.sqrt(s2 / Lo), unit = spread2d / 100;
  let R, t, w = new Float64Array(E);
  if (prev) { R = prev.R.slice(); t = prev.t.slice(); w.set(prev.w); } else {
    // frontal, at the distance where the neutral's landmarks have the observed spread (as fit_head)
    let ax = 0, ay = 0, az = 0;
    for (let l = 0; l < Lo; l++) { ax += m.neutral[3 * l]; ay += m.neutral[3 * l + 1]; az += m.neutral[3 * l + 2]; }
    ax /= Lo; ay /= Lo; az /= Lo;
    let s3 = 0;
    for (let l = 0; l < Lo; l++) s3 += (m.neutral[3 * l] - ax) ** 2 + (m.neutral[3 * l + 1] - ay) ** 2;
    const z0 = f * Math.sqrt(s3 / Lo) / spread2d;
    R = [1, 0, 0, 0, 1, 0, 0, 0, 1];
    t = [(mx - cx) * z0 / f - ax, -(my - cy) * z0 / f - ay, -z0 - az];
  }
  const p0 = prev ? { RT: [0, 3, 6, 1, 4, 7, 2, 5, 8].map((i) => prev.R[i]), t: prev.t, w: prev.w } : null;
  const q = new Float64Array(3 * L), H = new Float64Array(n * n), g = new Float64Array(n);
  const rowU = new Float64Array(n), rowV = new Float64Array(n);
  const piv = m.pivot, D = m.deltas, N0 = m.neutral, LL = 3 * L;
  const DL = m.deltasByLandmark; // [L][E][3]
  // cost (and, with `grad`, the Gauss-Newton normal equations) at R, t, w
  const evaluate = (R, t, w, grad) => {
    for (let i = 0; i < LL; i++) q[i] = N0[i];
    for (let e = 0; e < E; e++) {
      const we = w[e];
      if (we !== 0) { const o = e * LL; for (let i = 0; i < LL; i++) q[i] += we * D[o + i]; }
    }
    if (grad) { H.fill(0); g.fill(0); }
    let cost = 0, err = 0;
    for (let k = 0; k < U.length; k++) {
      const l = U[k], o = 3 * l;
      const a0 = q[o] - piv[0], a1 = q[o + 1] - piv[1], a2 = q[o + 2] - piv[2];
      const r0 = R[0] * a0 + R[1] * a1 + R[2] * a2, r1 = R[3] * a0 + R[4] * a1 + R[5] * a2, r2 = R[6] * a0 + R[7] * a1 + R[8] * a2;
      const px = r0 + piv[0] + t[0], py = r1 + piv[1] + t[1], pz = r2 + piv[2] + t[2];
      const zc = Math.max(-pz, 1e-3), xc = px, yc = -py;
      const u = f * xc / zc + cx, v = f * yc / zc + cy;
      const ru = (u - obs[2 * l]) / unit, rv = (v - obs[2 * l + 1]) / unit;
      err += Math.hypot(u - obs[2 * l], v - obs[2 * l + 1]);
      const aru = Math.abs(ru), arv = Math.abs(rv);
      cost += aru <= delta ? 0.5 * ru * ru : delta * (aru - 0.5 * delta);
      cost += arv <= delta ? 0.5 * rv * rv : delta * (arv - 0.5 * delta);
      if (!grad) continue;
      // each residual's row, times its IRLS weight of the Huber loss; d(residual)/d(world point) in residual
      // units: u (gx, 0, gzu), v (0, gy, gzv); rotation (left increment): (R a) x grad; translation: grad;
      // weights: (R^T grad) . delta_e,l
      const omU = aru <= delta ? 1 : delta / aru, omV = arv <= delta ? 1 : delta / arv;
      const gx = f / zc / unit, gy = -f / zc / unit, gzu = f * xc / (zc * zc) / unit, gzv = f * yc / (zc * zc) / unit;
      rowU[0] = r1 * gzu; rowU[1] = r2 * gx - r0 * gzu; rowU[2] = -r1 * gx; rowU[3] = gx; rowU[4] = 0; rowU[5] = gzu;
      rowV[0] = r1 * gzv - r2 * gy; rowV[1] = -r0 * gzv; rowV[2] = r0 * gy; rowV[3] = 0; rowV[4] = gy; rowV[5] = gzv;
      const u0 = R[0] * gx + R[6] * gzu, u1 = R[1] * gx + R[7] * gzu, u2 = R[2] * gx + R[8] * gzu;
      const v0 = R[3] * gy + R[6] * gzv, v1 = R[4] * gy + R[7] * gzv, v2 = R[5] * gy + R[8] * gzv;
      for (let e = 0, d = l * E * 3; e < E; e++, d += 3) {
        rowU[6 + e] = u0 * DL[d] + u1 * DL[d + 1] + u2 * DL[d + 2];
        rowV[6 + e] = v0 * DL[d] + v1 * DL[d + 1] + v2 * DL[d + 2];
      }
      for (let i = 0; i < n; i++) { // the two rank-1 updates in one pass (the same sums in the same order)
        const a = omU * rowU[i], b = omV * rowV[i], Hi = i * n;
        g[i] = g[i] + a * ru + b * rv;
        for (let j = i; j < n; j++) H[Hi + j] = H[Hi + j] + a * rowU[j] + b * rowV[j];
      }
    }
    for (let e = 0; e < E; e++) cost += 0.5 * w[e];
    if (grad) for (let e = 0; e < E; e++) g[6 + e] += 0.5;
    if (p0 && smooth > 0) {
      const rot = matrixAxisAngle(mat3Mul(R, p0.RT)); // the turn since the previous frame
      for (let k = 0; k < 3; k++) {
        cost += smooth * (100 * rot[k] ** 2 + 0.3 * (t[k] - p0.t[k]) ** 2);
        if (grad) { g[k] += 2 * smooth * 100 * rot[k]; H[k * n + k] += 2 * smooth * 100; g[3 + k] += 2 * smooth * 0.3 * (t[k] - p0.t[k]); H[(3 + k) * n + 3 + k] += 2 * smooth * 0.3; }
      }
      for (let e = 0; e < E; e++) {
        cost += smooth * 30 * (w[e] - p0.w[e]) ** 2;
        if (grad) { g[6 + e] += 2 * smooth * 30 * (w[e] - p0.w[e]); H[(6 + e) * n + 6 + e] += 2 * smooth * 30; }
      }
    }
    if (grad) for (let i = 0; i < n; i++) for (let j = 0; j < i; j++) H[i * n + j] = H[j * n + i];
    return { cost, errorPx: err / U.length };
  };
  const iterations = opts.iterations || (prev ? 5 : 40);
  const poseOnly = prev ? 0 : Math.floor(iterations / 3); // a cold start finds the pose first
  let cur = evaluate(R, t, w, true), lambda = 1e-3, it = 0;
  const A = new Float64Array(n * n), bvec = new Float64Array(n), idx = new Int32Array(n);
  for (; it < iterations; it++) {
    // free variables: the pose, and the weights not held at a bound by their gradient
    let k = 0;
    for (let i = 0; i < n; i++) {
      if (i >= 6 && (it < poseOnly || (w[i - 6] <= 0 && g[i] > 0) || (w[i - 6] >= 1 && g[i] < 0))) continue;
      idx[k++] = i;
    }
    let accepted = false;
    for (let tries = 0; tries < 6 && !accepted; tries++) {
      for (let a = 0; a < k; a++) {
        for (let c = 0; c < k; c++) A[a * k + c] = H[idx[a] * n + idx[c]];
        A[a * k + a] += lambda * (H[idx[a] * n + idx[a]] + 1e-9);
        bvec[a] = -g[idx[a]];
      }
      const step = choleskySolve(A, bvec, k);
      if (!step) { lambda *= 10; continue; }
      // the pose is always free: step[0..2] turn R (left increment), step[3..5] move t
      const R2 = mat3Mul(axisAngleMatrix([step[0], step[1], step[2]]), R), t2 = [t[0] + step[3], t[1] + step[4], t[2] + step[5]];
      const w2 = Float64Array.from(w);
      for (let a = 6; a < k; a++) w2[idx[a] - 6] = Math.min(1, Math.max(0, w[idx[a] - 6] + step[a]));
      const trial = evaluate(R2, t2, w2, false);
      if (trial.cost <= cur.cost) {
        const rel = (cur.cost - trial.cost) / Math.max(cur.cost, 1e-12);
        R = R2; t = t2; w = w2; lambda = Math.max(lambda * 0.3, 1e-7); accepted = true;
        cur = evaluate(R, t, w, true);
        if (rel < 1e-7 && it >= poseOnly) it = iterations; // converged
      } else lambda *= 10;
    }
    if (!accepted) break;
  }
  return { R, rot: matrixAxisAngle(R), t, w, cost: cur.cost, errorPx: cur.errorPx, iterations: Math.min(it, iterations) };
}

/** Solution x of the symmetric positive definite system A x = b (k x k, row-major; A is overwritten), or null. */
function choleskySolve(A, b, k) {
  for (let j = 0; j < k; j++) {
    let s = A[j * k + j];
    for (let p = 0; p < j; p++) s -= A[j * k + p] ** 2;
    if (!(s > 0)) return null;
    const d = Math.sqrt(s);
    A[j * k + j] = d;
    for (let i = j + 1; i < k; i++) {
      let v = A[i * k + j];
      for (let p = 0; p < j; p++) v -= A[i * k + p] * A[j * k + p];
      A[i * k + j] = v / d;
    }
  }
  const x = new Float64Array(k);
  for (let i = 0; i < k; i++) { let v = b[i]; for (let p = 0; p < i; p++) v -= A[i * k + p] * x[p]; x[i] = v / A[i * k + i]; }
  for (let i = k - 1; i >= 0; i--) { let v = x[i]; for (let p = i + 1; p < k; p++) v -= A[p * k + i] * x[p]; x[i] = v / A[i * k + i]; }
  return x;
}

/** Quaternion xyzw of a row-major 3x3 rotation. */
export function matrixQuaternion(R) {
  const tr = R[0] + R[4] + R[8];
  let x, y, z, w;
  if (tr > 0) { const s = 2 * Math.sqrt(tr + 1); w = s / 4; x = (R[7] - R[5]) / s; y = (R[2] - R[6]) / s; z = (R[3] - R[1]) / s; }
  else if (R[0] > R[4] && R[0] > R[8]) { const s = 2 * Math.sqrt(1 + R[0] - R[4] - R[8]); w = (R[7] - R[5]) / s; x = s / 4; y = (R[1] + R[3]) / s; z = (R[2] + R[6]) / s; }
  else if (R[4] > R[8]) { const s = 2 * Math.sqrt(1 + R[4] - R[0] - R[8]); w = (R[2] - R[6]) / s; x = (R[1] + R[3]) / s; y = s / 4; z = (R[5] + R[7]) / s; }
  else { const s = 2 * Math.sqrt(1 + R[8] - R[0] - R[4]); w = (R[3] - R[1]) / s; x = (R[2] + R[6]) / s; y = (R[5] + R[7]) / s; z = s / 4; }
  return [x, y, z, w];
}

/** Why the camera could not be opened, in words (a getUserMedia error). */
export function cameraErrorText(err) {
  const name = err && err.name;
  if (name === "NotAllowedError" || name === "SecurityError") return "camera access was refused: allow the camera for this page (the icon in the address bar) and press webcam again";
  if (name === "NotFoundError" || name === "OverconstrainedError") return "no camera found: plug one in (or free it) and press webcam again";
  if (name === "NotReadableError" || name === "AbortError") return "the camera is busy (another program or tab is using it) or failed to start";
  return `the camera could not be opened (${name || "error"}: ${err && err.message ? err.message : err})`;
}

/** Drawing-buffer pixels at most while the webcam drives the avatar and its draws are slow (the median of
 * the first solutions' draws, issued -> rendered, over WEBCAM_SLOW_DRAW_MS): the page draws a smaller image
 * and the browser scales it up to the canvas's CSS size, and blends in 8 bits (no float target and
 * composite pass; URL `camfloat=1` keeps them). URL `campixels=N` sets the cap and applies both however fast
 * the draws are (0: no cap). Under software WebGL the draw's cost follows its pixels (bench/reports/viewer.md,
 * webcam mode); with the webcam off the page draws as ever. */
export const WEBCAM_PIXELS = 50000;
export const WEBCAM_SLOW_DRAW_MS = 20;

/**
 * The canvas's drawing buffer: device pixels per CSS pixel are the screen's, capped by the quality setting
 * and a pixel budget (`budget`); `cap` > 0 (webcam mode) caps the buffer's pixels further (below one device
 * pixel per CSS pixel if need be). Returns {w, h} (the buffer) and {fullW, fullH} (without `cap`: the size
 * the view readout names).
 */
export function drawingSize(cssW, cssH, deviceRatio, quality, budget, cap = 0) {
  let dpr = Math.min(deviceRatio || 1, quality || 2);
  const css = Math.max(cssW * cssH, 1);
  if (css * dpr * dpr > budget) dpr = Math.max(1, Math.sqrt(budget / css));
  const fullW = Math.round(cssW * dpr), fullH = Math.round(cssH * dpr);
  if (!(cap > 0) || fullW * fullH <= cap) return { w: fullW, h: fullH, fullW, fullH };
  const s = Math.sqrt(cap / Math.max(fullW * fullH, 1));
  return { w: Math.max(1, Math.floor(fullW * s)), h: Math.max(1, Math.floor(fullH * s)), fullW, fullH };
}

/** Webcam mode re-sorts the Gaussians only when the head turned (quaternion angle, rad) or moved (its
 * translation, in the avatar's bounding radius) or a morph weight changed past these since the last sort. */
export const WEBCAM_RESORT = { angle: 0.02, move: 0.01, weight: 0.05 };
/** ... and a new order (or new shadow maps) is drawn by itself only once no solution came for this long (ms). */
export const WEBCAM_SETTLE_MS = 150;
/** While the webcam drives the avatar, the key light's height maps are rebuilt at most this often (ms): a
 * build costs a trained head's shadow worker about as much CPU as a draw, and the webcam's frames share the
 * CPU with it (bench/reports/viewer.md, webcam mode). */
export const WEBCAM_SHADOW_MS = 250;

/** Whether webcam pose `p` ({weights, rotation: {rotation xyzw, translation} | null}) is within
 * WEBCAM_RESORT of `s` (the pose last sorted), `radius` the avatar's bounding radius. */
export function webcamPoseClose(s, p, radius) {
  if (!s || !p || s.weights.length !== p.weights.length) return false;
  for (let i = 0; i < p.weights.length; i++) if (Math.abs(p.weights[i] - s.weights[i]) > WEBCAM_RESORT.weight) return false;
  const a = s.rotation, c = p.rotation;
  if (!a !== !c) return false;
  if (!a) return true;
  const dot = Math.abs(a.rotation[0] * c.rotation[0] + a.rotation[1] * c.rotation[1] + a.rotation[2] * c.rotation[2] + a.rotation[3] * c.rotation[3]);
  if (2 * Math.acos(Math.min(1, dot)) > WEBCAM_RESORT.angle) return false;
  if (!a.translation !== !c.translation) return false;
  if (a.translation && Math.hypot(...[0, 1, 2].map((k) => a.translation[k] - c.translation[k])) > WEBCAM_RESORT.move * radius) return false;
  return true;
}

/** What the webcam mode's landmarker runs by default (the page's URL overrides them: `camrefine=0`, `camsize=N`, `camcpu=0`). */
export const WEBCAM_DEFAULTS = {
  // MediaPipe's attention model (478 points, lips and eyes refined); false: the plain 468-point mesh, 1-2 ms
  // less a frame at 256 px, but it misses a smile by 0.3-0.4 (bench/reports/viewer.md, webcam mode)
  refine: true,
  size: 256, // the camera frame is scaled to this many pixels on its long side before the landmarker (0: as it comes)
  cpu: true, // the models run on the CPU (WebAssembly, XNNPACK) rather than in WebGL, where each pass reads pixels back
};

/**
 * The page's webcam mode: the camera's frames -> MediaPipe face landmarks (the @mediapipe/face_mesh
 * files beside the page; nothing is sent anywhere) -> solveFace -> the avatar's morph weights and head
 * rotation and translation (smoothed). `onPose(weights, rotation xyzw, frameTime, translation)` is called per
 * solved frame; the translation (cm, the head's axes: x right, y up, z towards the camera) is the head's
 * move since the first solved frame (or since "neutral").
 * `options`: WEBCAM_DEFAULTS's keys.
 */
export class WebcamDriver {
  constructor(doc, b, onPose, onStatus, options = {}) {
    this.doc = doc; this.b = b; this.onPose = onPose; this.onStatus = onStatus;
    this.options = { ...WEBCAM_DEFAULTS, ...options };
    this.busy = false; this.pending = null; this.canvas = null;
    this.running = false; this.stream = null; this.mesh = null; this.prev = null; this.smoothW = null; this.smoothR = null;
    this.neutral = null; this.lastRaw = null; this.alpha = 0.6;
    // mirrored (default, as the preview and a selfie camera): turn left and the avatar turns to the
    // screen's left, smile on your left and it smiles on the screen's left (its right): the turn is
    // reflected in the x = 0 plane of the head (y and z of the axis-angle negated), _L and _R swapped
    this.mirror = true;
    this.t0 = null; this.smoothT = null;
    const names = b.webcam ? b.webcam.names : [];
    this.swap = names.map((n, e) => {
      const other = n.endsWith("_L") ? `${n.slice(0, -2)}_R` : n.endsWith("_R") ? `${n.slice(0, -2)}_L` : n;
      const i = names.indexOf(other);
      return i < 0 ? e : i;
    });
    // frames: solved; camera: camera frames seen; dropped: those replaced by a newer one while the landmarker was busy
    // latencyMs: frame in -> the avatar's draw calls issued; renderedMs: -> its pixels rendered (a fence);
    // idleMs: from one landmark pass's end to the next one's start (waiting for a new camera frame)
    // drawMs: the avatar's draw, its draw calls issued -> its pixels rendered (the page's cap on slow draws reads it)
    this.stats = { frames: 0, camera: 0, dropped: 0, solveMs: [], landmarkMs: [], latencyMs: [], renderedMs: [], drawMs: [], idleMs: [],
                   startedAt: 0, lost: 0, weights: [] };
  }

  async loadLandmarker() {
    const folder = this.b.webcam.landmarker.folder, win = this.doc.defaultView;
    if (!win.FaceMesh) {
      await new Promise((resolve, reject) => {
        const s = this.doc.createElement("script");
        s.src = `${folder}/face_mesh.js`;
        s.onload = resolve;
        s.onerror = () => reject(new Error(`the face landmarker (${folder}/face_mesh.js) is missing beside this page: write it again with meshsplat view --webcam`));
        this.doc.head.appendChild(s);
      });
    }
    const mesh = new win.FaceMesh({ locateFile: (f) => `${folder}/${f}` });
    // one face; the attention model unless `refine` is false (the solve needs no iris: `used` is the first 468 points)
    mesh.setOptions({ maxNumFaces: 1, refineLandmarks: !!this.options.refine, useCpuInference: !!this.options.cpu,
                      minDetectionConfidence: 0.5, minTrackingConfidence: 0.5 });
    mesh.onResults((r) => this.results(r));
    await mesh.initialize();
    return mesh;
  }

  async start(video) {
    const nav = this.doc.defaultView.navigator;
    if (this.doc.location && this.doc.location.protocol === "file:") {
      throw new Error("webcam mode needs the page served over http (a browser keeps a file:// page from loading the face model): run meshsplat view ... --webcam --serve, then open http://127.0.0.1:8000/");
    }
    if (!nav.mediaDevices || !nav.mediaDevices.getUserMedia) {
      throw new Error("this browser gives no camera to this page (no navigator.mediaDevices: the page must come from http://127.0.0.1, localhost or https)");
    }
    this.onStatus("asking for the camera…");
    try {
      this.stream = await nav.mediaDevices.getUserMedia({ video: { width: { ideal: 640 }, height: { ideal: 480 }, facingMode: "user" }, audio: false });
    } catch (err) { throw new Error(cameraErrorText(err)); }
    video.srcObject = this.stream;
    await video.play();
    this.onStatus("loading the face model (on this machine; nothing leaves it)…");
    if (!this.mesh) this.mesh = await this.loadLandmarker();
    this.video = video; this.running = true; this.prev = null; this.stats.startedAt = performance.now();
    this.onStatus("looking for a face…");
    this.loop();
  }

  // every camera frame is noted as it arrives (requestVideoFrameCallback); the landmarker takes the
  // newest one whenever it is free, so a frame that arrives while it is busy is dropped, never queued
  // (its time of arrival is "frame in"); the page draws the latest solution on its next animation frame
  loop() {
    const v = this.video;
    const watch = () => {
      if (!this.running) return;
      if (v.requestVideoFrameCallback) v.requestVideoFrameCallback(onFrame); else requestAnimationFrame(onFrame);
    };
    const onFrame = () => {
      if (!this.running) return;
      this.stats.camera++;
      if (this.pending !== null) this.stats.dropped++;
      this.pending = performance.now();
      if (!this.busy) this.pump();
      watch();
    };
    watch();
  }

  // landmark the newest pending frame, and again while newer ones came in meanwhile
  async pump() {
    const v = this.video;
    this.busy = true;
    try {
      while (this.running && this.pending !== null) {
        this.frameIn = this.pending; this.pending = null;
        if (!(v.readyState >= 2 && v.videoWidth > 0)) continue;
        this.sentAt = performance.now();
        if (this.doneAt !== undefined) this.stats.idleMs.push(this.sentAt - this.doneAt);
        this.frameW = v.videoWidth; this.frameH = v.videoHeight;
        await this.mesh.send({ image: this.input(v) });
        this.doneAt = performance.now();
      }
    } catch (err) {
      this.onStatus(`face landmarker failed: ${err.message || err}`); this.stop();
    } finally { this.busy = false; }
  }

  // the frame the landmarker sees: scaled to `size` pixels on its long side (the landmarks come back
  // normalised to the frame, so they scale back to the camera's pixels as they are)
  input(v) {
    const W = this.frameW, H = this.frameH, size = this.options.size;
    const s = size > 0 ? Math.min(1, size / Math.max(W, H)) : 1;
    if (s >= 1) return v;
    if (!this.canvas) this.canvas = this.doc.createElement("canvas");
    const c = this.canvas, w = Math.max(1, Math.round(W * s)), h = Math.max(1, Math.round(H * s));
    if (c.width !== w || c.height !== h) { c.width = w; c.height = h; this.ctx = null; }
    if (!this.ctx) this.ctx = c.getContext("2d", { alpha: false, desynchronized: true });
    this.ctx.drawImage(v, 0, 0, w, h);
    return c;
  }

  results(r) {
    if (!this.running) return;
    const t1 = performance.now(), m = this.b.webcam, faces = r.multiFaceLandmarks;
    this.stats.landmarkMs.push(t1 - this.sentAt);
    const given = faces && faces.length ? Math.min(faces[0].length, m.L) : 0;
    if (!given || given <= m.usedMax) {
      this.stats.lost++; this.prev = null; this.onStatus("no face in view"); return;
    }
    const W = this.frameW, H = this.frameH, obs = new Float64Array(2 * given);
    for (let l = 0; l < given; l++) { const p = faces[0][l]; obs[2 * l] = p.x * W; obs[2 * l + 1] = p.y * H; }
    const sol = solveFace(m, obs, W, H, this.prev, { smooth: this.prev ? 0.1 : 0 });
    this.prev = sol;
    this.lastRaw = sol.w;
    let w = sol.w;
    if (this.neutral) w = w.map((x, e) => Math.min(1, Math.max(0, (x - this.neutral[e]) / Math.max(1 - this.neutral[e], 1e-3))));
    const a = this.alpha; // exponential smoothing of what is shown
    this.smoothW = this.smoothW ? this.smoothW.map((x, e) => x + a * (w[e] - x)) : Float64Array.from(w);
    let rot = sol.rot;
    if (this.mirror) { w = this.swap.map((i) => w[i]); rot = [rot[0], -rot[1], -rot[2]]; }
    this.smoothR = this.smoothR ? this.smoothR.map((x, k) => x + a * (rot[k] - x)) : rot.slice();
    const solveMs = performance.now() - t1;
    this.stats.solveMs.push(solveMs); this.stats.frames++;
    this.stats.weights.push({ t: this.frameIn, w: Array.from(sol.w), rot: sol.rot, err: sol.errorPx });
    for (const k of ["solveMs", "landmarkMs", "latencyMs", "renderedMs", "drawMs", "idleMs", "weights"]) if (this.stats[k].length > 600) this.stats[k].shift();
    this.lastRotation = matrixQuaternion(axisAngleMatrix(this.smoothR)); // the head node's (xyzw)
    if (!this.t0) this.t0 = sol.t.slice();
    const move = [0, 1, 2].map((k) => sol.t[k] - this.t0[k]);
    if (this.mirror) move[0] = -move[0];
    this.smoothT = this.smoothT ? this.smoothT.map((x, k) => x + a * (move[k] - x)) : move;
    this.lastTranslation = this.smoothT.slice();
    this.onPose(this.smoothW, this.lastRotation, this.frameIn, this.lastTranslation);
    this.onStatus(`${this.stats.frames} frames · landmarks ${(t1 - this.sentAt).toFixed(0)} ms · solve ${solveMs.toFixed(1)} ms · error ${sol.errorPx.toFixed(1)} px`);
  }

  /** The current raw weights become the neutral face (subtracted from then on), the current place the head's rest. */
  calibrate() {
    if (this.lastRaw) this.neutral = Float64Array.from(this.lastRaw);
    if (this.prev) { this.t0 = this.prev.t.slice(); this.smoothT = null; }
  }

  stop() {
    this.running = false; this.pending = null;
    if (this.stream) for (const t of this.stream.getTracks()) t.stop();
    this.stream = null; this.prev = null; this.smoothW = null; this.smoothR = null; this.t0 = null; this.smoothT = null;
  }
}

// ------------------------------------------------------------------ page UI
function decodeBase64(text) {
  const bin = atob(text.replace(/\s+/g, ""));
  const out = new Uint8Array(bin.length);
  for (let i = 0; i < bin.length; i++) out[i] = bin.charCodeAt(i);
  return out;
}

function el(doc, tag, attrs, parent) {
  const e = doc.createElement(tag);
  Object.assign(e, attrs || {});
  if (parent) parent.appendChild(e);
  return e;
}

/** Start the viewer in a page holding #avatar-header (JSON) and #avatar-data (base64 avatar.bin). */
export function startViewer(doc) {
  const $ = (id) => doc.getElementById(id);
  if (typeof window !== "undefined") window.meshsplatStarted = true;
  let header, bytes;
  try { header = JSON.parse($("avatar-header").textContent); } catch (err) {
    throw new Error("this page's data header is damaged (not JSON): the page was cut or edited; write it again with meshsplat view");
  }
  const problem = headerProblem(header);
  if (problem) throw new Error(problem);
  try { bytes = decodeBase64($("avatar-data").textContent); } catch (err) {
    throw new Error("this page's avatar data is damaged or cut short (not base64): get the whole file again");
  }
  const b = decodeBundle(header, bytes);
  if ($("loading")) $("loading").hidden = true;
  const params = new URLSearchParams(doc.location ? doc.location.search : "");
  const canvas = $("canvas");
  const renderer = new SplatRenderer(canvas, b, { floatTarget: params.get("float") !== "0", allFaces: params.get("mesh") === "all" });
  const poser = new FramePoser(b);
  const live = b.driver.kind === "gltf";
  const cam0 = header.camera;
  // the home view: the bundle's camera, moved back on a narrower screen (a phone held upright) so that
  // the subject fits across as it did in the bundle's frame
  const aspect = canvas.clientWidth / Math.max(canvas.clientHeight, 1), aspect0 = cam0.width / cam0.height;
  const homeDist = cam0.distance * (aspect > 0 && aspect < aspect0 ? aspect0 / aspect : 1);
  const cam = { az: cam0.azimuth_deg, el: cam0.elevation_deg, dist: homeDist, center: cam0.center.slice() };
  // zoom and pan limits from the subject's size: its canonical mesh's bounding sphere
  let lo = [Infinity, Infinity, Infinity], hi = [-Infinity, -Infinity, -Infinity];
  for (let i = 0; i < b.cano.length; i += 3) for (let k = 0; k < 3; k++) { lo[k] = Math.min(lo[k], b.cano[i + k]); hi[k] = Math.max(hi[k], b.cano[i + k]); }
  const radius = Math.max(0.5 * Math.hypot(hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2]), 1e-9);
  const limits = { minDist: 0.2 * radius, maxDist: Math.max(20 * radius, 4 * homeDist), pan: 1.5 * radius };
  const clampView = () => {
    cam.dist = Math.min(limits.maxDist, Math.max(limits.minDist, cam.dist));
    cam.el = Math.max(-89, Math.min(89, cam.el));
    const d = [0, 1, 2].map((k) => cam.center[k] - cam0.center[k]), len = Math.hypot(...d);
    if (len > limits.pan) for (let k = 0; k < 3; k++) cam.center[k] = cam0.center[k] + d[k] * limits.pan / len;
  };
  const hashView = parseView(doc.location ? doc.location.hash : "");
  if (hashView) { cam.az = hashView.az; cam.el = hashView.el; cam.dist = hashView.dist; cam.center = hashView.center.slice(); }
  // the page's own timers (the last 1,000 frames and sorts, ms) for the status line and bench/viewer.py
  const timings = { main: [], sort: [], key: [], firstReadyMs: null }; // key: the key light's height maps (CPU, worker)
  const record = (list, ms) => { list.push(ms); if (list.length > 1000) list.shift(); };
  const still = params.get("frame") !== null || params.get("time") !== null;
  const clips = live ? b.rig.clips : [];
  const clipParam = params.get("clip");
  const state = {
    frame: Math.min(Math.max(parseInt(params.get("frame") || "0", 10) || 0, 0), Math.max(b.T - 1, 0)),
    clip: live ? Math.max(0, clips.findIndex((c) => c.name === (clipParam || b.driver.clip))) : null,
    time: parseFloat(params.get("time") || "0") || 0, speed: 1,
    weights: live ? new Float64Array(b.rig.defaultWeights.length).fill(NaN) : null,
    playing: !still && params.get("play") !== "0" && (live ? clips.length > 0 : b.T > 1),
    white: (params.get("bg") || header.background || "white") !== "black",
    poseKey: "", sortedKey: null, drawnKey: null, pendingKey: null, sortMs: 0, moved: Infinity, lastNow: null,
    shadowKey: null, shadowPending: null, shadowAt: -Infinity, // the pose whose height maps are uploaded / being built (model.occlusion=key), when asked
    camSorted: null, camPoseKey: null, camPoseAt: 0, drawnBase: null, // webcam mode: the pose last sorted, the newest solution's key and time
  };
  for (const kv of (params.get("morph") || "").split(",").filter(Boolean)) { // ?morph=INDEX:WEIGHT,...
    const [i, w] = kv.split(":").map(Number);
    if (live && i >= 0 && i < state.weights.length) state.weights[i] = w;
  }
  const sorter = new DepthSorter(b, (r) => {
    if (r === null) { state.pendingKey = null; return; }
    if (state.pendingKey === null) return;
    renderer.setOrder(r.order, r.n);
    sorter.recycle(r.order);
    state.sortedKey = state.pendingKey; state.pendingKey = null; state.sortMs = r.ms; state.moved = r.moved;
    record(timings.sort, r.ms);
  }, params.get("worker") !== "0");
  const mapper = renderer.key ? new ShadowMapper(b, (r) => {
    if (r === null) { state.shadowPending = null; return; }
    renderer.setKeyMaps(r);
    mapper.recycle(r.depth);
    state.shadowKey = state.shadowPending; state.shadowPending = null;
    record(timings.key, r.ms);
  }, params.get("worker") !== "0") : null;
  const noUi = params.get("ui") === "0";
  if (noUi) $("ui").style.display = "none";
  // small screens: one row of controls until "more" is opened; the status line on request (?stats=1, i)
  const small = (window.innerWidth || 1000) < 600 || (window.innerHeight || 1000) < 500;
  const more = $("more"), menu = $("menu");
  const setMore = (open) => { more.hidden = !open; menu.setAttribute("aria-expanded", String(open)); menu.textContent = open ? "less" : "more"; };
  setMore(!small);
  menu.onclick = () => setMore(more.hidden);
  $("stats").hidden = params.get("stats") !== "1";
  const hint = $("hint");
  let hintSeen = false;
  try { hintSeen = window.localStorage.getItem("meshsplat-hint") === "seen"; } catch (err) { /* storage off */ }
  hint.hidden = noUi || hintSeen || params.get("hint") === "0";
  if (window.matchMedia && window.matchMedia("(pointer: coarse)").matches) {
    $("hinttext").textContent = "one finger: turn · two fingers: move and pinch to zoom · double tap: reset";
  }
  $("hintclose").onclick = () => { hint.hidden = true; try { window.localStorage.setItem("meshsplat-hint", "seen"); } catch (err) { /* storage off */ } };
  const slider = $("frame"), play = $("play"), bg = $("bg"), info = $("info"), stats = $("stats");
  $("title").textContent = header.title || "meshsplat avatar";
  const clipLength = () => (live && clips.length ? clips[state.clip].duration : 0);
  let clipSel = null, speedSel = null;
  const morphSliders = []; // [weight index, slider]: sliders follow the clip until moved
  if (live) {
    slider.step = "any";
    clipSel = el(doc, "select", { title: "clip" });
    clips.forEach((c, i) => el(doc, "option", { value: String(i), textContent: c.name }, clipSel));
    clipSel.value = String(state.clip);
    speedSel = el(doc, "select", { title: "speed" });
    [0.25, 0.5, 1, 2].forEach((s) => el(doc, "option", { value: String(s), textContent: `${s}x` }, speedSel));
    speedSel.value = "1";
    $("more").prepend(clipSel, speedSel);
    clipSel.onchange = () => { state.clip = parseInt(clipSel.value, 10); state.time = 0; syncUi(); };
    speedSel.onchange = () => { state.speed = parseFloat(speedSel.value); };
    const nMorph = b.rig.defaultWeights.length;
    const toggle = nMorph ? el(doc, "button", { textContent: `${nMorph} morph targets` }, $("ui")) : null;
    const panel = el(doc, "div", { id: "morphs" }, $("ui"));
    if (toggle) { // long lists (an ARKit face has 50+) start folded
      panel.hidden = nMorph > 12 || small; // never over the face on a phone until asked for
      toggle.onclick = () => { panel.hidden = !panel.hidden; };
      $("viewline").before(toggle);
    }
    const prefix = b.rig.groups.length > 1;
    for (const g of b.rig.groups) {
      g.names.forEach((name, m) => {
        const i = g.weight_base + m;
        const label = el(doc, "label", { textContent: `${prefix ? `${g.node_name}: ` : ""}${name} ` }, panel);
        const s = el(doc, "input", { type: "range", min: "0", max: "1", step: "0.01", title: `${g.node_name}: ${name}` }, label);
        s.value = String(Number.isNaN(state.weights[i]) ? b.rig.defaultWeights[i] : state.weights[i]);
        s.oninput = () => { state.weights[i] = parseFloat(s.value); };
        morphSliders.push([i, s]);
        const reset = el(doc, "button", { textContent: "clip", title: "back to the clip's weight" }, label);
        reset.onclick = () => { state.weights[i] = NaN; };
      });
    }
  }
  // webcam mode (bundles written with --webcam): the face in the camera drives the morph targets of
  // the solve's ARKit names and, for a blend-shape head, the head node's rotation
  const cam_ = { driver: null, weights: null, rotation: null, frameIn: null, key: 0, slow: false };
  if (live && b.webcam) {
    const btn = $("webcam"), panel = $("campanel"), status = $("camstatus"), video = $("camvideo");
    btn.hidden = false;
    const say = (text, bad) => { status.textContent = text; status.classList.toggle("bad", !!bad); };
    const targets = header.webcam.targets;
    const headNode = b.driver.source === "blendshapes" ? 0 : null;
    const headScale = headNode !== null && b.webcam.headSize ? boxDiagonal(b.rig.base) / b.webcam.headSize : 0;
    const stop = () => {
      if (cam_.driver) cam_.driver.stop();
      cam_.weights = null; cam_.rotation = null; cam_.frameIn = null; cam_.slow = false;
      panel.hidden = true; btn.textContent = "webcam"; btn.setAttribute("aria-pressed", "false");
    };
    btn.onclick = async () => {
      if (cam_.driver && cam_.driver.running) { stop(); return; }
      panel.hidden = false; btn.textContent = "stop webcam"; btn.setAttribute("aria-pressed", "true");
      $("hint").hidden = true; // the camera panel takes its corner
      cam_.driver = cam_.driver || new WebcamDriver(doc, b, (w, q, frameIn, move) => {
        const over = new Float64Array(b.rig.defaultWeights.length); // untracked morphs at 0
        targets.forEach((i, e) => { if (i >= 0) over[i] = w[e]; });
        // the head node at its rest place plus the face's move, in the avatar's units (its size over the ICT head's)
        const translation = headNode !== null && move && headScale ? [0, 1, 2].map((k) => b.rig.trs[10 * headNode + k] + headScale * move[k]) : undefined;
        cam_.weights = over; cam_.rotation = headNode === null ? null : { node: headNode, rotation: q, translation };
        cam_.frameIn = frameIn; cam_.key++;
      }, (text) => say(text), {
        ...(params.has("camrefine") ? { refine: params.get("camrefine") === "1" } : {}),
        ...(params.has("camsize") ? { size: parseInt(params.get("camsize"), 10) || 0 } : {}),
        ...(params.has("camcpu") ? { cpu: params.get("camcpu") === "1" } : {}),
      });
      state.playing = false; syncUi();
      try { await cam_.driver.start(video); } catch (err) { cam_.driver.stop(); say(String(err.message || err), true); btn.textContent = "webcam"; }
    };
    $("camstop").onclick = stop;
    $("camneutral").onclick = () => cam_.driver && cam_.driver.calibrate();
    $("cammirror").onclick = () => {
      if (!cam_.driver) return;
      cam_.driver.mirror = !cam_.driver.mirror; cam_.driver.smoothW = null; cam_.driver.smoothR = null; cam_.driver.smoothT = null;
      $("cammirror").textContent = cam_.driver.mirror ? "mirrored" : "as seen";
      $("cammirror").setAttribute("aria-pressed", String(cam_.driver.mirror));
    };
  }
  const syncUi = () => {
    if (live) { slider.max = String(clipLength()); slider.value = String(state.time); }
    else { slider.max = String(b.T - 1); slider.value = String(state.frame); }
    play.textContent = state.playing ? "pause" : "play";
    bg.textContent = state.white ? "black bg" : "white bg";
    doc.body.classList.toggle("dark", !state.white);
  };
  play.onclick = () => { state.playing = !state.playing; syncUi(); };
  slider.oninput = () => {
    state.playing = false;
    if (live) state.time = parseFloat(slider.value); else state.frame = parseInt(slider.value, 10);
    syncUi();
  };
  bg.onclick = () => { state.white = !state.white; syncUi(); };
  const resetView = () => {
    cam.az = cam0.azimuth_deg; cam.el = cam0.elevation_deg; cam.dist = homeDist; cam.center = cam0.center.slice();
  };
  // pan: the centre moves in the view plane so that the subject follows the pointer (dx, dy CSS pixels)
  const pan = (dx, dy) => {
    const vm = orbitViewmat(cam.center, cam.dist, cam.az, cam.el, cam0.up, cam0.front);
    const s = 2 * cam.dist * Math.tan(cam0.fov_deg * Math.PI / 360) / Math.max(canvas.clientHeight, 1);
    for (let k = 0; k < 3; k++) cam.center[k] -= s * (dx * vm[k] + dy * vm[4 + k]);
    clampView();
  };
  canvas.addEventListener("dblclick", (e) => { e.preventDefault(); resetView(); });
  canvas.addEventListener("contextmenu", (e) => e.preventDefault());
  const fs = $("fullscreen");
  if (!doc.fullscreenEnabled) fs.hidden = true;
  const toggleFullscreen = () => {
    if (!doc.fullscreenEnabled) return;
    if (doc.fullscreenElement) doc.exitFullscreen(); else doc.documentElement.requestFullscreen().catch(() => {});
  };
  fs.onclick = toggleFullscreen;
  const quality = $("quality");
  if (params.get("dpr")) quality.value = params.get("dpr");
  const PIXEL_BUDGET = 4e6; // canvas pixels at most (a 3x phone would draw 3 million at full resolution)
  // webcam mode's cap on the drawing buffer: on slow draws (?campixels=N: always; 0: never); off while the webcam is stopped
  const camPixelsSet = params.has("campixels");
  const camPixels = camPixelsSet ? Math.max(0, parseFloat(params.get("campixels")) || 0) : WEBCAM_PIXELS;
  const camFloat = params.get("camfloat") === "1"; // ... and blends in 8 bits then, unless ?camfloat=1
  $("reset").onclick = resetView;
  // one pointer (mouse or finger) drags to orbit; two fingers pinch to zoom (distance ratio); the
  // wheel zooms; a double tap, the reset button or "r" gives the default view back
  const pointers = new Map(); // pointerId -> [x, y]
  let pinch = 0, lastTap = null, press = null; // press: [time, x, y] of a lone finger, null once it moved or had company
  let mid = null, panning = false; // two fingers' midpoint (they pan as they move); a right/middle/shift mouse drag pans
  const spread = () => { const [a, c] = [...pointers.values()]; return Math.hypot(a[0] - c[0], a[1] - c[1]); };
  const midpoint = () => { const [a, c] = [...pointers.values()]; return [(a[0] + c[0]) / 2, (a[1] + c[1]) / 2]; };
  canvas.addEventListener("pointerdown", (e) => {
    canvas.setPointerCapture(e.pointerId);
    pointers.set(e.pointerId, [e.clientX, e.clientY]);
    if (pointers.size === 2) { pinch = spread(); mid = midpoint(); }
    panning = e.pointerType === "mouse" && (e.button === 2 || e.button === 1 || e.shiftKey);
    press = pointers.size === 1 && e.pointerType === "touch" ? [e.timeStamp, e.clientX, e.clientY] : null;
  });
  const release = (e) => {
    if (!pointers.delete(e.pointerId)) return;
    if (pointers.size === 2) { pinch = spread(); mid = midpoint(); }
    if (e.type !== "pointerup" || !press || pointers.size > 0) return;
    const now = e.timeStamp; // a tap: short, still, alone; two taps close in time and place reset the view
    if (now - press[0] < 300) {
      if (lastTap && now - lastTap[0] < 400 && Math.hypot(press[1] - lastTap[1], press[2] - lastTap[2]) < 40) {
        resetView(); lastTap = null;
      } else lastTap = [now, press[1], press[2]];
    }
    press = null;
  };
  canvas.addEventListener("pointerup", release);
  canvas.addEventListener("pointercancel", release);
  canvas.addEventListener("pointermove", (e) => {
    const prev = pointers.get(e.pointerId);
    if (!prev) return;
    pointers.set(e.pointerId, [e.clientX, e.clientY]);
    if (press && Math.hypot(e.clientX - press[1], e.clientY - press[2]) > 10) press = null;
    if (pointers.size === 1 && panning) {
      pan(e.clientX - prev[0], e.clientY - prev[1]);
    } else if (pointers.size === 1) {
      cam.az -= 0.3 * (e.clientX - prev[0]);
      cam.el = Math.max(-89, Math.min(89, cam.el + 0.3 * (e.clientY - prev[1])));
    } else if (pointers.size === 2) {
      const d = spread(), m = midpoint();
      if (pinch > 0 && d > 0) cam.dist *= pinch / d; // fingers apart: closer
      if (mid) pan(m[0] - mid[0], m[1] - mid[1]); // both fingers moving together: move
      pinch = d; mid = m;
      clampView();
    }
  });
  canvas.addEventListener("wheel", (e) => { e.preventDefault(); cam.dist *= Math.exp(0.001 * e.deltaY); clampView(); },
                          { passive: false });
  // the space bar plays/pauses whatever has the focus (a focused button would otherwise take it)
  const isSpace = (e) => e.key === " " || e.code === "Space";
  doc.addEventListener("keydown", (e) => {
    if (isSpace(e)) { e.preventDefault(); if (!e.repeat) play.onclick(); return; }
    const tag = (e.target && e.target.tagName) || "";
    if (tag === "INPUT" || tag === "SELECT" || tag === "TEXTAREA" || e.ctrlKey || e.metaKey || e.altKey) return; // their own keys
    const step = e.shiftKey ? 1 : 5, keys = {
      ArrowLeft: () => { cam.az += step; }, ArrowRight: () => { cam.az -= step; },
      ArrowUp: () => { cam.el += step; }, ArrowDown: () => { cam.el -= step; },
      "+": () => { cam.dist *= 0.9; }, "=": () => { cam.dist *= 0.9; }, "-": () => { cam.dist /= 0.9; },
      r: resetView, f: toggleFullscreen, i: () => { $("stats").hidden = !$("stats").hidden; },
    };
    if (keys[e.key]) { e.preventDefault(); keys[e.key](); clampView(); }
  }, true);
  doc.addEventListener("keyup", (e) => { if (isSpace(e)) e.preventDefault(); }, true);
  // the view readout (render flags), the URL fragment that reopens it, and "copy view"
  const viewText = $("viewtext");
  let viewShown = "", hashAt = 0, readyView = null;
  const pageFolder = () => {
    const loc = doc.location;
    if (!loc || loc.protocol !== "file:") return "FOLDER";
    const path = decodeURIComponent(loc.pathname);
    return path.slice(0, path.lastIndexOf("/")) || "/";
  };
  const viewCopy = (vs) => {
    const loc = doc.location, url = loc ? `${loc.href.split("#")[0]}#${vs}` : `#${vs}`;
    return `${url}\nmeshsplat render RUN --camera 'page:${pageFolder()}#${vs}' --out OUT`;
  };
  $("copyview").onclick = async () => {
    const text = viewCopy(viewShown), btn = $("copyview");
    try { await navigator.clipboard.writeText(text); btn.textContent = "copied"; } catch (err) {
      viewText.value = text; viewText.select(); // no clipboard here (file:// in some browsers): select it to copy
      btn.textContent = doc.execCommand && doc.execCommand("copy") ? "copied" : "select + copy";
    }
    setTimeout(() => { btn.textContent = "copy view"; }, 1500);
  };
  // what the page shows, for tests and benchmarks (read-only use)
  // floatTarget: whether the splats blend in floating point (false: the 8-bit fallback, or ?float=0);
  // timeDraws(n, float) (bench/viewer_float.py): the last frame drawn again n times, each waited for by
  // a 1-pixel readback, its times (ms); `float` false: through the 8-bit path this once (the float
  // target when true and the page has one), then the canvas gets the page's own path back
  let lastDraw = null;
  const timeDraws = (n, float) => {
    const gl = renderer.gl, px = new Uint8Array(4), out = [], own = renderer.floatTarget;
    if (float !== undefined) renderer.floatTarget = own && float;
    for (let i = 0; lastDraw && i < n; i++) {
      const t0 = performance.now();
      renderer.draw(...lastDraw);
      gl.readPixels(0, 0, 1, 1, gl.RGBA, gl.UNSIGNED_BYTE, px);
      out.push(performance.now() - t0);
    }
    renderer.floatTarget = own;
    if (lastDraw) { renderer.draw(...lastDraw); gl.readPixels(0, 0, 1, 1, gl.RGBA, gl.UNSIGNED_BYTE, px); } // waited for: not in the next call's first time
    return out;
  };
  window.meshsplatViewer = { view: cam, limits, get viewString() { return viewShown; }, state, timings, timeDraws, get webcam() { return cam_.driver; }, get floatTarget() { return renderer.floatTarget; },
                            get shadowWorker() { return mapper ? mapper.inWorker : null; } };
  syncUi();
  let fpsCount = 0, fpsT = performance.now(), fps = 0, mainMs = 0, pose = null;
  const tick = (now) => {
    const t0 = performance.now();
    const dt = state.lastNow === null ? 0 : Math.max(0, now - state.lastNow) / 1000;
    state.lastNow = now;
    if (state.playing) {
      if (live) {
        const len = clipLength();
        state.time = len > 0 ? (state.time + dt * state.speed) % len : 0;
      } else {
        state.acc = (state.acc || 0) + dt * header.fps;
        const steps = Math.floor(state.acc);
        state.acc -= steps;
        state.frame = (state.frame + steps) % b.T;
      }
      slider.value = String(live ? state.time : state.frame);
    }
    // device pixels per CSS pixel: the screen's, capped by the quality setting and a pixel budget; while
    // the webcam drives the avatar, the drawing buffer's pixels are capped further (camPixels; CSS scales it up)
    const webcamOn = cam_.weights !== null;
    if (webcamOn && !cam_.slow && cam_.driver && cam_.driver.stats.drawMs.length >= 3) { // slow draws: the cap stays on until stop
      const d = cam_.driver.stats.drawMs.slice(-5).sort((x, y) => x - y);
      cam_.slow = d[d.length >> 1] > WEBCAM_SLOW_DRAW_MS;
    }
    const cheap = webcamOn && (camPixelsSet || cam_.slow); // the webcam's cheaper draw: capped buffer, 8-bit blending
    renderer.blend8 = cheap && !camFloat;
    const size = drawingSize(canvas.clientWidth, canvas.clientHeight, window.devicePixelRatio || 1, parseFloat(quality.value) || 2,
                             PIXEL_BUDGET, cheap ? camPixels : 0);
    const w = size.w, h = size.h;
    if (canvas.width !== w || canvas.height !== h) { canvas.width = w; canvas.height = h; }
    const viewmat = orbitViewmat(cam.center, cam.dist, cam.az, cam.el, cam0.up, cam0.front);
    const vs = viewString(cam, cam0.fov_deg, size.fullW, size.fullH); // the view at the page's own size, capped or not
    if (vs !== viewShown) {
      viewShown = vs;
      if (doc.activeElement !== viewText) viewText.value = viewFlags(cam, cam0.fov_deg, size.fullW, size.fullH);
    }
    // the address holds the view once it left the home view (throttled): a reload or a shared link opens it
    const atHome = cam.az === cam0.azimuth_deg && cam.el === cam0.elevation_deg && cam.dist === homeDist &&
      cam.center.every((x, k) => x === cam0.center[k]);
    const wanted = atHome ? "" : `#${vs}`;
    if (doc.location && doc.location.hash !== wanted && now - hashAt > 250 && window.history && window.history.replaceState) {
      hashAt = now;
      try { window.history.replaceState(null, "", wanted || doc.location.href.split("#")[0]); } catch (err) { /* opaque origins */ }
    }
    const K = intrinsics(w, h, cam0.fov_deg);
    const poseKey = webcamOn ? `webcam|${cam_.key}` : live ? `${state.clip}|${(clips.length ? clips[state.clip].start : 0) + state.time}|${Array.from(state.weights).join()}`
                         : String(state.frame);
    if (poseKey !== state.poseKey) {
      if (webcamOn) {
        pose = poser.rig(null, 0, cam_.weights, cam_.rotation || undefined);
        renderer.setRig(pose.rig);
        for (const [i, s] of morphSliders) s.value = String(cam_.weights[i]);
      } else if (live) {
        pose = poser.rig(clips.length ? state.clip : null, (clips.length ? clips[state.clip].start : 0) + state.time, state.weights);
        renderer.setRig(pose.rig);
        for (const [i, s] of morphSliders) if (Number.isNaN(state.weights[i])) s.value = String(pose.rig.weights[i]);
      } else {
        pose = poser.frame(state.frame);
        renderer.setVertices(pose.verts);
      }
      state.poseKey = poseKey;
    }
    // the shadow worker builds the key light's height maps of the newest pose whenever it is free (while the
    // webcam drives the avatar, at most every WEBCAM_SHADOW_MS)
    if (mapper && poseKey !== state.shadowKey && state.shadowPending === null && !(webcamOn && now - state.shadowAt < WEBCAM_SHADOW_MS)) {
      state.shadowAt = now;
      state.shadowPending = poseKey; // before the request: without a worker the result comes back inside it
      if (!mapper.request(pose)) state.shadowPending = null;
    }
    // the worker sorts whenever the drawn pose or view differs from the sorted one and it is free; in webcam
    // mode a pose within WEBCAM_RESORT of the one last sorted keeps that order (its key stands for it)
    const camPose = webcamOn ? { weights: cam_.weights, rotation: cam_.rotation } : null;
    if (!webcamOn) state.camSorted = null;
    else if (poseKey !== state.camPoseKey) { state.camPoseKey = poseKey; state.camPoseAt = now; }
    const sortPoseKey = webcamOn && state.camSorted && webcamPoseClose(state.camSorted.pose, camPose, radius) ? state.camSorted.key : poseKey;
    const key = `${sortPoseKey}#${Array.from(viewmat).join()}`;
    if (key !== state.sortedKey && state.pendingKey === null) {
      state.pendingKey = key; // before the request: without a worker the result comes back inside it
      if (webcamOn) state.camSorted = { pose: camPose, key: sortPoseKey };
      if (!sorter.request(pose, viewmat)) state.pendingKey = null;
    }
    // draw when the pose, view, order, shadows, background or size changed (a still page stays idle); in webcam
    // mode a new order or new height maps alone wait for the next solution's draw while solutions keep coming
    // (one draw each)
    const drawBase = `${poseKey}|${key}|${state.white}|${w}x${h}|${renderer.blend8}`;
    const drawKey = `${drawBase}|${state.sortedKey}|${state.shadowKey}`;
    const orderOnly = webcamOn && state.drawnBase === drawBase && now - state.camPoseAt < WEBCAM_SETTLE_MS;
    if (drawKey !== state.drawnKey && !orderOnly && !(mapper && state.shadowKey === null)) { // not before the first height maps
      lastDraw = [viewmat, K, state.white ? [1, 1, 1] : [0, 0, 0]];
      renderer.draw(...lastDraw);
      state.drawnKey = drawKey; state.drawnBase = drawBase;
      if (webcamOn && cam_.frameIn !== null && cam_.driver) { // frame in -> avatar drawn (its draw calls issued)
        const st = cam_.driver.stats, frameIn = cam_.frameIn, gl = renderer.gl;
        const issued = performance.now();
        st.latencyMs.push(issued - frameIn); cam_.frameIn = null;
        if (gl.fenceSync) { // ... and -> its pixels rendered (a fence after the draw signals)
          const fence = gl.fenceSync(gl.SYNC_GPU_COMMANDS_COMPLETE, 0);
          gl.flush();
          const poll = () => {
            if (gl.getSyncParameter(fence, gl.SYNC_STATUS) !== gl.SIGNALED) { setTimeout(poll, 1); return; }
            const t = performance.now();
            st.renderedMs.push(t - frameIn); st.drawMs.push(t - issued); gl.deleteSync(fence);
          };
          setTimeout(poll, 0);
        }
      }
      mainMs = performance.now() - t0;
      record(timings.main, mainMs);
    }
    fpsCount++;
    if (now - fpsT > 500) { fps = 1000 * fpsCount / (now - fpsT); fpsCount = 0; fpsT = now; }
    info.textContent = live ? `${state.time.toFixed(2)} s` : `frame ${state.frame + 1}/${b.T}`;
    stats.textContent = `${fps.toFixed(0)} fps · ${b.N} Gaussians (${renderer.visible} drawn) · main ${mainMs.toFixed(1)} ms` +
      ` · sort ${state.sortMs.toFixed(1)} ms (${sorter.inWorker ? "worker" : "main thread"})` +
      (mapper ? ` · shadow maps ${renderer.keyMs.toFixed(1)} ms (${mapper.inWorker ? "worker" : "main thread"})` : "") +
      (renderer.floatTarget && !renderer.blend8 ? "" : " · 8-bit blending (bright overlaps clamped)") +
      ` · centres moved ≤ ${Number.isFinite(state.moved) ? state.moved.toExponential(1) : "-"} between sorts` +
      (key === state.sortedKey ? "" : " · order stale") + (mapper && state.shadowKey !== poseKey ? " · shadow stale" : "");
    // ready (for screenshots) once the drawn order belongs to the drawn pose and view, and so do its height maps
    if (key === state.sortedKey && (!mapper || state.shadowKey === poseKey) && state.drawnKey === drawKey) {
      if (timings.firstReadyMs === null) timings.firstReadyMs = performance.now(); // since navigation start
      doc.body.dataset.ready = "1";
      readyView = vs;
    } else if (doc.body.dataset.ready === "1" && vs !== readyView) doc.body.dataset.ready = "0"; // a new view on its way
    requestAnimationFrame(tick);
  };
  requestAnimationFrame(tick);
}

if (typeof document !== "undefined" && document.getElementById("avatar-data")) {
  try {
    startViewer(document);
  } catch (err) {
    const el = document.getElementById("error");
    if (el) { el.textContent = String(err && err.message ? err.message : err); el.style.display = "block"; }
    throw err;
  }
}
