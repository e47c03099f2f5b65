// meshsplat WebGL2 viewer: poses mesh-embedded Gaussians on the GPU every frame and splats them.
//
// Per frame the main thread does per-VERTEX work only: it decodes the frame's vertices, computes
// vertex normals, vertex quaternions and face area ratios (poseMesh) and uploads them to float
// textures. The vertex shader evaluates each Gaussian's embedding (Phong point + d*n, blended
// rotation, area scale) from those textures and projects it; one instanced draw call. The depth
// sort runs in a Web Worker (created from a Blob URL of inline source, so it works from file://),
// on the posed centres, with a 16-bit counting sort; the main thread never waits for it.
//
// Pure functions (decodeBundle, frameVertices, poseMesh, poseGaussians, gaussianDepths, sortDepths,
// orbitViewmat, intrinsics) mirror meshsplat.mesh.geometry / meshsplat.embedding /
// meshsplat.gaussians.compose and run under Node for the tests and bench/viewer.py. The UI starts
// only in a page that holds the embedded avatar data. Cameras follow the project convention:
// world->camera viewmat in OpenCV axes (x right, y down, z forward), pinhole K, pixel centres at
// +0.5. Matrices are row-major flat arrays.

export const SH_C0 = 0.28209479177387814;
const EPS = 1e-12;            // meshsplat.mesh.geometry._EPS
const EPS2D = 0.3;            // 2D covariance dilation (pixels^2), as the rasterizer
const ALPHA_THRESHOLD = 1 / 255;
const ALPHA_MAX = 0.999;
const MAX_EXTEND = 3.33;
const FOV_CLAMP_MARGIN = 0.3;
const NEAR_PLANE = 0.01;
export const TEX_WIDTH = 2048; // width of every data texture (texel i at (i % W, i / W))

// ------------------------------------------------------------------ bundle decoding
const TYPED = { float32: Float32Array, uint32: Uint32Array, int16: Int16Array };

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

/** Typed-array views of avatar.bin (`bytes`: ArrayBuffer or Uint8Array) laid out per `header`. */
export function decodeBundle(header, bytes) {
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
    faces: arr.faces, cano: arr.canonical_vertices, frames: arr.frames, packed: arr.gaussians,
    ...unpackGaussians(arr.gaussians, N),
  };
  // canonical per-face frames (constant) and areas
  const cf = faceGeometry(b, Float64Array.from(b.cano));
  b.canoFrames = cf.frames;
  b.canoAreas = cf.areas;
  // largest |u| + |v| + |1-u-v| and |d|: bound how far a centre's depth moves with the vertices
  let baryMax = 1, dMax = 0;
  for (let g = 0; g < N; g++) {
    const u = b.uv[2 * g], v = b.uv[2 * g + 1];
    baryMax = Math.max(baryMax, Math.abs(u) + Math.abs(v) + Math.abs(1 - u - v));
    dMax = Math.max(dMax, Math.abs(b.d[g]));
  }
  b.baryMax = baryMax; b.dMax = dMax;
  return b;
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
function faceGeometry(b, p, out) {
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

/** Rotation matrix (row-major, 9 numbers from `m` at `o`) -> unit quaternion wxyz with w >= 0. */
function matrixToQuat(m, o, q, qo) {
  const m00 = m[o], m01 = m[o + 1], m02 = m[o + 2], m10 = m[o + 3], m11 = m[o + 4], m12 = m[o + 5];
  const m20 = m[o + 6], m21 = m[o + 7], m22 = m[o + 8];
  const c = [1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22];
  let best = 0;
  for (let i = 1; i < 4; i++) if (c[i] > c[best]) best = i; // first maximum, as torch.argmax
  let w, x, y, z;
  if (best === 0) { w = c[0]; x = m21 - m12; y = m02 - m20; z = m10 - m01; }
  else if (best === 1) { w = m21 - m12; x = c[1]; y = m10 + m01; z = m02 + m20; }
  else if (best === 2) { w = m02 - m20; x = m10 + m01; y = c[2]; z = m12 + m21; }
  else { w = m10 - m01; x = m20 + m02; y = m21 + m12; z = c[3]; }
  let r = 1 / Math.max(Math.sqrt(w * w + x * x + y * y + z * z), 1e-12);
  if (w * r < 0) r = -r;
  q[qo] = w * r; q[qo + 1] = x * r; q[qo + 2] = y * r; q[qo + 3] = z * r;
}

/**
 * Posed per-vertex normals [V*3], quaternions [V*4] (wxyz) and per-face area ratios [F] of the
 * posed vertices `p` [V*3]. `ws` (optional): the result of a previous call, whose buffers are reused.
 */
export function poseMesh(b, p, ws) {
  const V = b.V, F = b.F, f = b.faces;
  ws = ws || { geo: undefined, qf: new Float64Array(F * 4), areaRatio: new Float64Array(F),
               normals: new Float64Array(V * 3), wmax: new Float64Array(V), ref: new Int32Array(V),
               quats: new Float64Array(V * 4) };
  const g = ws.geo = faceGeometry(b, p, ws.geo);
  const qf = ws.qf, ratio = ws.areaRatio, rot = new Float64Array(9);
  const cf = b.canoFrames, pf = g.frames;
  for (let k = 0; k < F; k++) {
    const o = 9 * k;
    for (let i = 0; i < 3; i++) for (let j = 0; j < 3; j++) // R = F_posed F_cano^T
      rot[3 * i + j] = pf[o + 3 * i] * cf[o + 3 * j] + pf[o + 3 * i + 1] * cf[o + 3 * j + 1] + pf[o + 3 * i + 2] * cf[o + 3 * j + 2];
    matrixToQuat(rot, 0, qf, 4 * k);
    const a0 = b.canoAreas[k];
    ratio[k] = a0 > EPS ? g.areas[k] / a0 : 1;
  }
  const nrm = ws.normals, wmax = ws.wmax, ref = ws.ref, acc = ws.quats;
  nrm.fill(0); wmax.fill(-1); ref.fill(0); acc.fill(0);
  // area-weighted vertex normals (sum of cross products) and reference face per vertex
  for (let k = 0; k < F; k++) {
    for (let j = 0; j < 3; j++) {
      const v = f[3 * k + j];
      nrm[3 * v] += g.cross[3 * k]; nrm[3 * v + 1] += g.cross[3 * k + 1]; nrm[3 * v + 2] += g.cross[3 * k + 2];
      if (g.areas[k] >= wmax[v]) { wmax[v] = g.areas[k]; ref[v] = k; } // ties -> largest face index
    }
  }
  for (let v = 0; v < V; v++) {
    const x = nrm[3 * v], y = nrm[3 * v + 1], z = nrm[3 * v + 2];
    const r = 1 / Math.sqrt(Math.max(x * x + y * y + z * z, EPS * EPS));
    nrm[3 * v] = x * r; nrm[3 * v + 1] = y * r; nrm[3 * v + 2] = z * r;
  }
  // vertex quaternion: area-weighted sum of incident face quaternions, signs aligned to the reference face
  for (let k = 0; k < F; k++) {
    const w = g.areas[k], q = 4 * k;
    for (let j = 0; j < 3; j++) {
      const v = f[3 * k + j], r = 4 * ref[v];
      const dot = qf[q] * qf[r] + qf[q + 1] * qf[r + 1] + qf[q + 2] * qf[r + 2] + qf[q + 3] * qf[r + 3];
      const s = dot < 0 ? -w : w;
      for (let i = 0; i < 4; i++) acc[4 * v + i] += s * qf[q + i];
    }
  }
  for (let v = 0; v < V; v++) {
    const o = 4 * v, n2 = acc[o] ** 2 + acc[o + 1] ** 2 + acc[o + 2] ** 2 + acc[o + 3] ** 2;
    if (n2 > 1e-30) {
      const r = 1 / Math.max(Math.sqrt(n2), 1e-15);
      for (let i = 0; i < 4; i++) acc[o + i] *= r;
    } else { acc[o] = 1; acc[o + 1] = 0; acc[o + 2] = 0; acc[o + 3] = 0; }
  }
  return ws;
}

// ------------------------------------------------------------------ Gaussians (CPU reference)
/**
 * CPU reference of what the vertex shader computes (tests, benchmarks; the page does not call it).
 * Posed Gaussians of frame `t` (or of explicit vertices `verts` [V*3] when given):
 * { means [N*3], quats [N*4] wxyz, scales [N*3], cov [N*6] (xx, xy, xz, yy, yz, zz) } as Float32Array.
 */
export function poseGaussians(b, t, verts, out) {
  const N = b.N, f = b.faces;
  const p = verts || frameVertices(b, t);
  const m = poseMesh(b, p);
  const mode = b.header.scale_mode;
  out = out || { means: new Float32Array(N * 3), quats: new Float32Array(N * 4), scales: new Float32Array(N * 3),
                 cov: new Float32Array(N * 6) };
  const vq = m.quats, vn = m.normals;
  for (let g = 0; g < N; g++) {
    const k = b.face[g], u = b.uv[2 * g], v = b.uv[2 * g + 1], wc = 1 - u - v;
    const ia = f[3 * k], ib = f[3 * k + 1], ic = f[3 * k + 2];
    // Phong point + displacement along the interpolated normal
    let nx = u * vn[3 * ia] + v * vn[3 * ib] + wc * vn[3 * ic];
    let ny = u * vn[3 * ia + 1] + v * vn[3 * ib + 1] + wc * vn[3 * ic + 1];
    let nz = u * vn[3 * ia + 2] + v * vn[3 * ib + 2] + wc * vn[3 * ic + 2];
    const rn = 1 / Math.sqrt(Math.max(nx * nx + ny * ny + nz * nz, EPS * EPS));
    nx *= rn; ny *= rn; nz *= rn;
    const d = b.d[g];
    out.means[3 * g] = u * p[3 * ia] + v * p[3 * ib] + wc * p[3 * ic] + d * nx;
    out.means[3 * g + 1] = u * p[3 * ia + 1] + v * p[3 * ib + 1] + wc * p[3 * ic + 1] + d * ny;
    out.means[3 * g + 2] = u * p[3 * ia + 2] + v * p[3 * ib + 2] + wc * p[3 * ic + 2] + d * nz;
    // delta_q: barycentric blend of the corner quaternions, signs aligned to corner a
    const qa = 4 * ia, qb = 4 * ib, qc = 4 * ic;
    let sb = 0, sc = 0;
    for (let i = 0; i < 4; i++) { sb += vq[qb + i] * vq[qa + i]; sc += vq[qc + i] * vq[qa + i]; }
    const wb = sb < 0 ? -v : v, wcc = sc < 0 ? -wc : wc;
    let dw = u * vq[qa] + wb * vq[qb] + wcc * vq[qc], dx = u * vq[qa + 1] + wb * vq[qb + 1] + wcc * vq[qc + 1];
    let dy = u * vq[qa + 2] + wb * vq[qb + 2] + wcc * vq[qc + 2], dz = u * vq[qa + 3] + wb * vq[qb + 3] + wcc * vq[qc + 3];
    const rd = 1 / Math.max(Math.sqrt(dw * dw + dx * dx + dy * dy + dz * dz), 1e-12);
    dw *= rd; dx *= rd; dy *= rd; dz *= rd;
    // q = delta_q ⊗ q_canonical (Hamilton product), normalized
    const cw = b.rot[4 * g], cx = b.rot[4 * g + 1], cy = b.rot[4 * g + 2], cz = b.rot[4 * g + 3];
    let qw = dw * cw - dx * cx - dy * cy - dz * cz, qx = dw * cx + dx * cw + dy * cz - dz * cy;
    let qy = dw * cy - dx * cz + dy * cw + dz * cx, qz = dw * cz + dx * cy - dy * cx + dz * cw;
    const rq = 1 / Math.max(Math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz), 1e-12);
    qw *= rq; qx *= rq; qy *= rq; qz *= rq;
    out.quats[4 * g] = qw; out.quats[4 * g + 1] = qx; out.quats[4 * g + 2] = qy; out.quats[4 * g + 3] = qz;
    // scale modulation by the face's area change
    const ratio = m.areaRatio[k];
    const fac = mode === "area" ? ratio : mode === "sqrt_area" ? Math.sqrt(Math.max(ratio, 0) + 1e-20) : 1;
    const s0 = b.scale[3 * g] * fac, s1 = b.scale[3 * g + 1] * fac, s2 = b.scale[3 * g + 2] * fac;
    out.scales[3 * g] = s0; out.scales[3 * g + 1] = s1; out.scales[3 * g + 2] = s2;
    // covariance R S S^T R^T
    const xx = qx * qx, yy = qy * qy, zz = qz * qz, xy = qx * qy, xz = qx * qz, yz = qy * qz;
    const wx = qw * qx, wy = qw * qy, wz = qw * qz;
    const r00 = (1 - 2 * (yy + zz)) * s0, r01 = 2 * (xy - wz) * s1, r02 = 2 * (xz + wy) * s2;
    const r10 = 2 * (xy + wz) * s0, r11 = (1 - 2 * (xx + zz)) * s1, r12 = 2 * (yz - wx) * s2;
    const r20 = 2 * (xz - wy) * s0, r21 = 2 * (yz + wx) * s1, r22 = (1 - 2 * (xx + yy)) * s2;
    const c = out.cov, o = 6 * g;
    c[o] = r00 * r00 + r01 * r01 + r02 * r02; c[o + 1] = r00 * r10 + r01 * r11 + r02 * r12;
    c[o + 2] = r00 * r20 + r01 * r21 + r02 * r22; c[o + 3] = r10 * r10 + r11 * r11 + r12 * r12;
    c[o + 4] = r10 * r20 + r11 * r21 + r12 * r22; c[o + 5] = r20 * r20 + r21 * r21 + r22 * r22;
  }
  return out;
}

// ------------------------------------------------------------------ cameras (as meshsplat.synth.rigs)
/** World->camera [16] row-major (OpenCV axes, +y up) of a camera orbiting `center` (angles in degrees). */
export function orbitViewmat(center, distance, azimuthDeg, elevationDeg) {
  const az = azimuthDeg * Math.PI / 180, el = elevationDeg * Math.PI / 180;
  const eye = [center[0] + distance * Math.cos(el) * Math.sin(az), center[1] + distance * Math.sin(el),
               center[2] + distance * Math.cos(el) * Math.cos(az)];
  const norm = (a) => { const l = Math.hypot(a[0], a[1], a[2]); return [a[0] / l, a[1] / l, a[2] / l]; };
  const cross = (a, c) => [a[1] * c[2] - a[2] * c[1], a[2] * c[0] - a[0] * c[2], a[0] * c[1] - a[1] * c[0]];
  const fwd = norm([center[0] - eye[0], center[1] - eye[1], center[2] - eye[2]]);
  let right = cross(fwd, [0, 1, 0]);
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

/** Pinhole [fx, fy, cx, cy] for a vertical field of view, principal point at the image centre. */
export function intrinsics(width, height, fovDeg) {
  const f = 0.5 * height / Math.tan(fovDeg * Math.PI / 360);
  return [f, f, width / 2, height / 2];
}

/**
 * Camera depth [N] (Float32Array) of every posed Gaussian centre, computed as the vertex shader
 * does: z of (Phong point + d * normalized interpolated normal), from the posed vertices `verts`
 * and vertex normals `normals` (both [V*3]). `g` holds face, uv, d of the Gaussians and the mesh
 * faces (a decoded bundle or the worker's copy). This is the worker's per-Gaussian work.
 */
export function gaussianDepths(g, verts, normals, viewmat, depth) {
  const N = g.N, f = g.faces, face = g.face, uv = g.uv, dd = g.d;
  const r0 = viewmat[8], r1 = viewmat[9], r2 = viewmat[10], t = viewmat[11];
  depth = depth || new Float32Array(N);
  for (let i = 0; i < N; i++) {
    const k = face[i], u = uv[2 * i], v = uv[2 * i + 1], w = 1 - u - v;
    const a = 3 * f[3 * k], b = 3 * f[3 * k + 1], c = 3 * f[3 * k + 2];
    const nx = u * normals[a] + v * normals[b] + w * normals[c];
    const ny = u * normals[a + 1] + v * normals[b + 1] + w * normals[c + 1];
    const nz = u * normals[a + 2] + v * normals[b + 2] + w * normals[c + 2];
    const s = dd[i] / Math.sqrt(Math.max(nx * nx + ny * ny + nz * nz, 1e-24));
    const x = u * verts[a] + v * verts[b] + w * verts[c] + s * nx;
    const y = u * verts[a + 1] + v * verts[b + 1] + w * verts[c + 1] + s * ny;
    const z = u * verts[a + 2] + v * verts[b + 2] + w * verts[c + 2] + s * nz;
    depth[i] = r0 * x + r1 * y + r2 * z + t;
  }
  return depth;
}

/**
 * Back-to-front order of the depths >= the near plane: one counting sort on 16-bit quantized depth
 * over the visible range (ties keep index order). Fills `order` [n]; returns the visible count.
 * `ws` (optional) holds reusable scratch {counts: Uint32Array(65536), bins: Uint16Array(n)}.
 */
export function sortDepths(depth, n, order, ws) {
  const NEAR = 0.01; // NEAR_PLANE, spelled out: this function also runs in the worker
  let lo = Infinity, hi = -Infinity;
  for (let g = 0; g < n; g++) {
    const z = depth[g];
    if (z >= NEAR) { if (z < lo) lo = z; if (z > hi) hi = z; }
  }
  const counts = ws && ws.counts ? ws.counts : new Uint32Array(65536);
  const bins = ws && ws.bins && ws.bins.length >= n ? ws.bins : new Uint16Array(n);
  counts.fill(0);
  const q = hi > lo ? 65535 / (hi - lo) : 0;
  let visible = 0;
  for (let g = 0; g < n; g++) {
    const z = depth[g];
    if (!(z >= NEAR)) continue;
    const bin = 65535 - Math.min(65535, Math.floor((z - lo) * q)); // far first; z >= lo
    bins[g] = bin; counts[bin]++; visible++;
  }
  for (let i = 1; i < 65536; i++) counts[i] += counts[i - 1];
  for (let g = n - 1; g >= 0; g--) if (depth[g] >= NEAR) order[--counts[bins[g]]] = g;
  return visible;
}

/** Back-to-front order of Gaussian centres `means` [n*3] for `viewmat`: float32 depth, then sortDepths. */
export function sortByDepth(means, n, viewmat, order, counts) {
  const depth = new Float32Array(n);
  const r0 = viewmat[8], r1 = viewmat[9], r2 = viewmat[10], t = viewmat[11];
  for (let g = 0; g < n; g++) depth[g] = r0 * means[3 * g] + r1 * means[3 * g + 1] + r2 * means[3 * g + 2] + t;
  order = order || new Uint32Array(n);
  return sortDepths(depth, n, order, { counts });
}
// ------------------------------------------------------------------ per-frame vertex data
/**
 * Texture data of a posed mesh: `verts` [V*4*3] (texels p, n, q per vertex: position and normal
 * with w = 0, quaternion wxyz) and `ratio` [F] (posed/canonical face area), float32.
 */
export function packVertexTexels(b, p, m, out) {
  const V = b.V, F = b.F;
  out = out || { verts: new Float32Array(texSize(3 * V) * 4), ratio: new Float32Array(texSize(F)) };
  const t = out.verts, n = m.normals, q = m.quats;
  for (let v = 0; v < V; v++) {
    const o = 12 * v;
    t[o] = p[3 * v]; t[o + 1] = p[3 * v + 1]; t[o + 2] = p[3 * v + 2];
    t[o + 4] = n[3 * v]; t[o + 5] = n[3 * v + 1]; t[o + 6] = n[3 * v + 2];
    t[o + 8] = q[4 * v]; t[o + 9] = q[4 * v + 1]; t[o + 10] = q[4 * v + 2]; t[o + 11] = q[4 * v + 3];
  }
  out.ratio.set(m.areaRatio);
  return out;
}

/** Texels of a TEX_WIDTH-wide texture holding `n` texels (whole rows). */
export function texSize(n) { return TEX_WIDTH * Math.max(1, Math.ceil(n / TEX_WIDTH)); }

/**
 * Bound on how far any Gaussian centre moved in camera depth between a sorted state and now:
 * baryMax * max_v |z_v - z_v'| + dMax * max_v |r3.n_v - r3'.n_v'| (vertex v, camera row 3 r3).
 * The first term is exact for the Phong point (a barycentric combination); the second is first
 * order in the normal change (the interpolated normal is renormalized). Pairs of Gaussians whose
 * depths differ by more than 2*delta (+ one 16-bit bin) are still drawn in the right order.
 */
export function depthDrift(b, verts, normals, viewmat, sorted) {
  if (!sorted) return Infinity;
  const r0 = viewmat[8], r1 = viewmat[9], r2 = viewmat[10], t = viewmat[11];
  const s = sorted.viewmat, s0 = s[8], s1 = s[9], s2 = s[10], st = s[11], P = sorted.verts, Nn = sorted.normals;
  let dz = 0, dn = 0;
  for (let i = 0; i < 3 * b.V; i += 3) {
    const z = r0 * verts[i] + r1 * verts[i + 1] + r2 * verts[i + 2] + t;
    const zs = s0 * P[i] + s1 * P[i + 1] + s2 * P[i + 2] + st;
    const n = r0 * normals[i] + r1 * normals[i + 1] + r2 * normals[i + 2];
    const ns = s0 * Nn[i] + s1 * Nn[i + 1] + s2 * Nn[i + 2];
    dz = Math.max(dz, Math.abs(z - zs)); dn = Math.max(dn, Math.abs(n - ns));
  }
  return b.baryMax * dz + b.dMax * dn;
}

// ------------------------------------------------------------------ sort worker
/** Source of the sort worker (inline, so that it can start from a Blob URL under file://). */
export const SORT_WORKER_SOURCE = `"use strict";
${gaussianDepths.toString()}
${sortDepths.toString()}
let G = null, depth = null, ws = null;
onmessage = (e) => {
  const m = e.data;
  if (m.type === "init") {
    G = m; depth = new Float32Array(m.N); ws = { counts: new Uint32Array(65536), bins: new Uint16Array(m.N) };
    return;
  }
  const t0 = performance.now();
  gaussianDepths(G, m.verts, m.normals, m.viewmat, depth);
  const order = new Uint32Array(G.N);
  const n = sortDepths(depth, G.N, order, ws);
  postMessage({ id: m.id, n, order, ms: performance.now() - t0 }, [order.buffer]);
};
`;

/** The depth sorter: a Web Worker when available, else the same functions on the calling thread. */
export class DepthSorter {
  constructor(b, onResult) {
    this.onResult = onResult; this.busy = false; this.nextId = 1; this.inWorker = false;
    const init = { type: "init", N: b.N, faces: b.faces, face: b.face, uv: b.uv, d: b.d };
    try {
      const url = URL.createObjectURL(new Blob([SORT_WORKER_SOURCE], { type: "text/javascript" }));
      this.worker = new Worker(url);
      this.worker.onmessage = (e) => { this.busy = false; this.onResult(e.data); };
      this.worker.onerror = (e) => { console.error("sort worker:", e.message); this.worker = null; this.busy = false; };
      this.worker.postMessage(init);
      this.inWorker = true;
    } catch (err) {
      console.warn("no Web Worker, sorting on the main thread:", err);
      this.worker = null; this.g = init;
      this.depth = new Float32Array(b.N); this.ws = { counts: new Uint32Array(65536), bins: new Uint16Array(b.N) };
    }
  }

  /** Request a sort of the pose (`verts`, `normals` float32 [V*3], not kept) seen from `viewmat`. */
  request(verts, normals, viewmat) {
    if (this.busy) return false;
    const msg = { type: "sort", id: this.nextId++, verts: verts.slice(), normals: normals.slice(),
                  viewmat: Array.from(viewmat) };
    this.busy = true;
    if (this.worker) {
      this.worker.postMessage(msg, [msg.verts.buffer, msg.normals.buffer]);
    } else {
      const t0 = performance.now();
      gaussianDepths(this.g, msg.verts, msg.normals, msg.viewmat, this.depth);
      const order = new Uint32Array(this.g.N);
      const n = sortDepths(this.depth, this.g.N, order, this.ws);
      this.busy = false;
      this.onResult({ id: msg.id, n, order, ms: performance.now() - t0 });
    }
    return msg;
  }
}

// ------------------------------------------------------------------ WebGL2 splatting
const VERT = `#version 300 es
precision highp float; precision highp int;
precision highp sampler2D; precision highp usampler2D;
layout(location=0) in vec2 corner;      // quad corner in {-1, 1}^2
layout(location=1) in uint gid;         // Gaussian index, instances in back-to-front order
uniform usampler2D gTex;                // 2 RGBA32UI texels per Gaussian (bundle.py pack_gaussians)
uniform usampler2D fTex;                // face -> vertex indices (a, b, c)
uniform sampler2D vTex;                 // 3 texels per posed vertex: position, normal, quaternion wxyz
uniform sampler2D rTex;                 // posed / canonical face area
uniform int scaleMode;                  // 0 none, 1 area, 2 sqrt_area
uniform mat3 R; uniform vec3 tr;        // world->camera (OpenCV)
uniform vec4 K;                         // fx, fy, cx, cy
uniform vec2 size;                      // width, height (pixels)
out vec2 offs; out vec3 conic; out vec4 col;
ivec2 at(int i) { return ivec2(i & ${TEX_WIDTH - 1}, i >> ${Math.log2(TEX_WIDTH)}); }
vec4 quatMul(vec4 a, vec4 b) {          // Hamilton product, w first
  return vec4(a.x * b.x - dot(a.yzw, b.yzw), a.x * b.yzw + b.x * a.yzw + cross(a.yzw, b.yzw));
}
void main() {
  int g = int(gid);
  uvec4 w0 = texelFetch(gTex, at(2 * g), 0), w1 = texelFetch(gTex, at(2 * g + 1), 0);
  vec2 uv = unpackHalf2x16(w0.y), dop = unpackHalf2x16(w0.z), rg = unpackHalf2x16(w0.w);
  vec4 qc = vec4(unpackHalf2x16(w1.x), unpackHalf2x16(w1.y));
  vec2 s01 = unpackHalf2x16(w1.z), s2b = unpackHalf2x16(w1.w);
  int k = int(w0.x);
  uvec4 fv = texelFetch(fTex, at(k), 0);
  int ia = 3 * int(fv.x), ib = 3 * int(fv.y), ic = 3 * int(fv.z);
  float u = uv.x, v = uv.y, w = 1.0 - u - v;
  // Phong point + d along the normalized interpolated normal (meshsplat.embedding)
  vec3 n = u * texelFetch(vTex, at(ia + 1), 0).xyz + v * texelFetch(vTex, at(ib + 1), 0).xyz
         + w * texelFetch(vTex, at(ic + 1), 0).xyz;
  n *= inversesqrt(max(dot(n, n), 1e-24));
  vec3 mean = u * texelFetch(vTex, at(ia), 0).xyz + v * texelFetch(vTex, at(ib), 0).xyz
            + w * texelFetch(vTex, at(ic), 0).xyz + dop.x * n;
  // delta_q: blend of the corner quaternions sign-aligned to corner a; q = delta_q (x) q_canonical
  vec4 qa = texelFetch(vTex, at(ia + 2), 0), qb = texelFetch(vTex, at(ib + 2), 0), qq = texelFetch(vTex, at(ic + 2), 0);
  vec4 dq = u * qa + (dot(qb, qa) < 0.0 ? -v : v) * qb + (dot(qq, qa) < 0.0 ? -w : w) * qq;
  dq /= max(length(dq), 1e-12);
  vec4 q = quatMul(dq, qc / max(length(qc), 1e-12));
  q /= max(length(q), 1e-12);
  float ratio = texelFetch(rTex, at(k), 0).x;
  float fac = scaleMode == 1 ? ratio : scaleMode == 2 ? sqrt(max(ratio, 0.0) + 1e-20) : 1.0;
  vec3 s = vec3(s01, s2b.x) * fac;
  vec3 mc = R * mean + tr;
  float op = dop.y;
  if (mc.z < ${NEAR_PLANE} || op < ${ALPHA_THRESHOLD}) { gl_Position = vec4(0.0, 0.0, 2.0, 1.0); return; }
  // world covariance M M^T with M = rot(q) diag(s)  (columns of rot(q) scaled)
  float qw = q.x, qx = q.y, qy = q.z, qz = q.w;
  mat3 M = mat3(1.0 - 2.0 * (qy * qy + qz * qz), 2.0 * (qx * qy + qw * qz), 2.0 * (qx * qz - qw * qy),
                2.0 * (qx * qy - qw * qz), 1.0 - 2.0 * (qx * qx + qz * qz), 2.0 * (qy * qz + qw * qx),
                2.0 * (qx * qz + qw * qy), 2.0 * (qy * qz - qw * qx), 1.0 - 2.0 * (qx * qx + qy * qy))
         * mat3(s.x, 0.0, 0.0, 0.0, s.y, 0.0, 0.0, 0.0, s.z);
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
  float a = c2[0][0] + ${EPS2D}, b = c2[1][0], c = c2[1][1] + ${EPS2D};
  float det = a * c - b * b;
  if (det <= 0.0) { gl_Position = vec4(0.0, 0.0, 2.0, 1.0); return; }
  conic = vec3(c, -b, a) / det;
  float extend = min(${MAX_EXTEND}, sqrt(2.0 * log(op / ${ALPHA_THRESHOLD})));
  vec2 radius = ceil(extend * sqrt(vec2(a, c)));
  vec2 m2 = K.xy * mc.xy * rz + K.zw;   // pixel position, y down
  offs = corner * radius;
  vec2 px = m2 + offs;
  gl_Position = vec4(2.0 * px.x / size.x - 1.0, 1.0 - 2.0 * px.y / size.y, 0.0, 1.0);
  col = vec4(rg, s2b.y, op);
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

function compile(gl, type, src) {
  const s = gl.createShader(type);
  gl.shaderSource(s, src);
  gl.compileShader(s);
  if (!gl.getShaderParameter(s, gl.COMPILE_STATUS)) throw new Error(gl.getShaderInfoLog(s));
  return s;
}

function dataTexture(gl, unit, internal, format, type, texels, data) {
  const tex = gl.createTexture();
  gl.activeTexture(gl.TEXTURE0 + unit);
  gl.bindTexture(gl.TEXTURE_2D, tex);
  for (const p of [gl.TEXTURE_MIN_FILTER, gl.TEXTURE_MAG_FILTER]) gl.texParameteri(gl.TEXTURE_2D, p, gl.NEAREST);
  gl.texImage2D(gl.TEXTURE_2D, 0, internal, TEX_WIDTH, texels / TEX_WIDTH, 0, format, type, data);
  return tex;
}

/**
 * Splat renderer on a WebGL2 canvas. Static textures: packed Gaussians and faces. Per pose:
 * `setPose(texels)` uploads the vertex and face-ratio textures; per sort: `setOrder(order, n)`;
 * `draw(viewmat, K, background)` issues one instanced draw call.
 */
export class SplatRenderer {
  constructor(canvas, b) {
    const gl = canvas.getContext("webgl2", { antialias: false, premultipliedAlpha: false, preserveDrawingBuffer: true });
    if (!gl) throw new Error("WebGL2 is not available in this browser");
    this.gl = gl; this.b = b;
    const prog = gl.createProgram();
    gl.attachShader(prog, compile(gl, gl.VERTEX_SHADER, VERT));
    gl.attachShader(prog, compile(gl, gl.FRAGMENT_SHADER, FRAG));
    gl.linkProgram(prog);
    if (!gl.getProgramParameter(prog, gl.LINK_STATUS)) throw new Error(gl.getProgramInfoLog(prog));
    this.prog = prog;
    const names = ["R", "tr", "K", "size", "gTex", "fTex", "vTex", "rTex", "scaleMode"];
    this.loc = Object.fromEntries(names.map((n) => [n, gl.getUniformLocation(prog, n)]));
    const maxTex = gl.getParameter(gl.MAX_TEXTURE_SIZE);
    if (texSize(2 * b.N) / TEX_WIDTH > maxTex) throw new Error(`${b.N} Gaussians exceed this GPU's texture size`);
    const gtex = new Uint32Array(texSize(2 * b.N) * 4);
    gtex.set(b.packed);
    dataTexture(gl, 0, gl.RGBA32UI, gl.RGBA_INTEGER, gl.UNSIGNED_INT, texSize(2 * b.N), gtex);
    const ftex = new Uint32Array(texSize(b.F) * 4);
    for (let k = 0; k < b.F; k++) for (let j = 0; j < 3; j++) ftex[4 * k + j] = b.faces[3 * k + j];
    dataTexture(gl, 1, gl.RGBA32UI, gl.RGBA_INTEGER, gl.UNSIGNED_INT, texSize(b.F), ftex);
    this.vTex = dataTexture(gl, 2, gl.RGBA32F, gl.RGBA, gl.FLOAT, texSize(3 * b.V), null);
    this.rTex = dataTexture(gl, 3, gl.R32F, gl.RED, gl.FLOAT, texSize(b.F), null);
    this.vao = gl.createVertexArray();
    gl.bindVertexArray(this.vao);
    const quad = gl.createBuffer();
    gl.bindBuffer(gl.ARRAY_BUFFER, quad);
    gl.bufferData(gl.ARRAY_BUFFER, new Float32Array([-1, -1, 1, -1, -1, 1, 1, 1]), gl.STATIC_DRAW);
    gl.enableVertexAttribArray(0);
    gl.vertexAttribPointer(0, 2, gl.FLOAT, false, 0, 0);
    this.orderBuf = gl.createBuffer();
    gl.bindBuffer(gl.ARRAY_BUFFER, this.orderBuf);
    gl.bufferData(gl.ARRAY_BUFFER, b.N * 4, gl.DYNAMIC_DRAW);
    gl.enableVertexAttribArray(1);
    gl.vertexAttribIPointer(1, 1, gl.UNSIGNED_INT, 0, 0);
    gl.vertexAttribDivisor(1, 1);
    gl.bindVertexArray(null);
    this.visible = 0;
  }

  setPose(texels) {
    const gl = this.gl, b = this.b;
    gl.activeTexture(gl.TEXTURE2);
    gl.bindTexture(gl.TEXTURE_2D, this.vTex);
    gl.texSubImage2D(gl.TEXTURE_2D, 0, 0, 0, TEX_WIDTH, texSize(3 * b.V) / TEX_WIDTH, gl.RGBA, gl.FLOAT, texels.verts);
    gl.activeTexture(gl.TEXTURE3);
    gl.bindTexture(gl.TEXTURE_2D, this.rTex);
    gl.texSubImage2D(gl.TEXTURE_2D, 0, 0, 0, TEX_WIDTH, texSize(b.F) / TEX_WIDTH, gl.RED, gl.FLOAT, texels.ratio);
  }

  setOrder(order, n) {
    const gl = this.gl;
    gl.bindBuffer(gl.ARRAY_BUFFER, this.orderBuf);
    gl.bufferSubData(gl.ARRAY_BUFFER, 0, order, 0, n);
    this.visible = n;
  }

  draw(viewmat, K, background) {
    const gl = this.gl, w = gl.canvas.width, h = gl.canvas.height;
    gl.viewport(0, 0, w, h);
    gl.clearColor(background[0], background[1], background[2], 1);
    gl.clear(gl.COLOR_BUFFER_BIT);
    gl.useProgram(this.prog);
    gl.disable(gl.DEPTH_TEST);
    gl.enable(gl.BLEND);
    gl.blendFunc(gl.ONE, gl.ONE_MINUS_SRC_ALPHA);
    const m = viewmat; // row-major -> GLSL column-major: pass transpose=false with columns
    gl.uniformMatrix3fv(this.loc.R, false, [m[0], m[4], m[8], m[1], m[5], m[9], m[2], m[6], m[10]]);
    gl.uniform3f(this.loc.tr, m[3], m[7], m[11]);
    gl.uniform4f(this.loc.K, K[0], K[1], K[2], K[3]);
    gl.uniform2f(this.loc.size, w, h);
    ["gTex", "fTex", "vTex", "rTex"].forEach((n, i) => gl.uniform1i(this.loc[n], i));
    gl.uniform1i(this.loc.scaleMode, { none: 0, area: 1, sqrt_area: 2 }[this.b.header.scale_mode]);
    gl.bindVertexArray(this.vao);
    if (this.visible > 0) gl.drawArraysInstanced(gl.TRIANGLE_STRIP, 0, 4, this.visible);
    gl.bindVertexArray(null);
  }
}

// ------------------------------------------------------------------ per-frame driver (main thread)
/**
 * Everything the main thread does for one frame, without WebGL: decode the frame's vertices,
 * pose the mesh (per vertex / per face), pack the texture data, and decide whether the current
 * sort is stale enough to request a new one. Shared by the page and bench/viewer.py.
 */
export class FramePoser {
  constructor(b) {
    this.b = b; this.p = new Float64Array(3 * b.V); this.ws = undefined; this.texels = undefined;
    this.verts32 = new Float32Array(3 * b.V); this.normals32 = new Float32Array(3 * b.V);
  }

  pose(t) {
    this.p = frameVertices(this.b, t, this.p);
    return this.poseVertices(this.p);
  }

  poseVertices(p) {
    this.ws = poseMesh(this.b, p, this.ws);
    this.texels = packVertexTexels(this.b, p, this.ws, this.texels);
    this.verts32.set(p); this.normals32.set(this.ws.normals);
    return this.texels;
  }

  /** Depth drift since `sorted` ({verts, normals, viewmat}) and whether it exceeds `tol`. */
  drift(viewmat, sorted) { return depthDrift(this.b, this.verts32, this.normals32, viewmat, sorted); }
}

// ------------------------------------------------------------------ page UI
function decodeBase64(text) {
  const bin = atob(text.replace(/\s+/g, ""));
  const out = new Uint8Array(bin.length);
  for (let i = 0; i < bin.length; i++) out[i] = bin.charCodeAt(i);
  return out;
}

/** Start the viewer in a page holding #avatar-header (JSON) and #avatar-data (base64 avatar.bin). */
export function startViewer(doc) {
  const $ = (id) => doc.getElementById(id);
  const header = JSON.parse($("avatar-header").textContent);
  const b = decodeBundle(header, decodeBase64($("avatar-data").textContent));
  const params = new URLSearchParams(doc.location ? doc.location.search : "");
  const canvas = $("canvas");
  const renderer = new SplatRenderer(canvas, b);
  const poser = new FramePoser(b);
  const cam0 = header.camera;
  const cam = { az: cam0.azimuth_deg, el: cam0.elevation_deg, dist: cam0.distance };
  const state = {
    frame: Math.min(Math.max(parseInt(params.get("frame") || "0", 10) || 0, 0), b.T - 1),
    playing: params.get("frame") === null && params.get("play") !== "0" && b.T > 1,
    white: (params.get("bg") || header.background || "white") !== "black",
    posedFrame: -1, t0: performance.now(), f0: 0,
    sorted: null, pending: null, drift: Infinity, sortMs: 0, sorts: 0,
  };
  // sort results arrive asynchronously; the order of the pose/view they were computed for is drawn
  const sorter = new DepthSorter(b, (r) => {
    const req = state.pending;
    state.pending = null;
    if (!req || r.id !== req.id) return;
    renderer.setOrder(r.order, r.n);
    state.sorted = req; state.sortMs = r.ms; state.sorts++;
  });
  if (params.get("ui") === "0") $("ui").style.display = "none";
  const slider = $("frame"), play = $("play"), bg = $("bg"), info = $("info"), stats = $("stats");
  slider.max = String(b.T - 1);
  $("title").textContent = header.title || "meshsplat avatar";
  const syncUi = () => {
    slider.value = String(state.frame);
    play.textContent = state.playing ? "pause" : "play";
    bg.textContent = state.white ? "black bg" : "white bg";
    doc.body.classList.toggle("dark", !state.white);
  };
  play.onclick = () => { state.playing = !state.playing; state.t0 = performance.now(); state.f0 = state.frame; syncUi(); };
  slider.oninput = () => { state.playing = false; state.frame = parseInt(slider.value, 10); syncUi(); };
  bg.onclick = () => { state.white = !state.white; syncUi(); };
  // orbit (drag) and zoom (wheel); "r" resets the default view
  let drag = null;
  canvas.addEventListener("pointerdown", (e) => { drag = [e.clientX, e.clientY]; canvas.setPointerCapture(e.pointerId); });
  canvas.addEventListener("pointerup", () => { drag = null; });
  canvas.addEventListener("pointermove", (e) => {
    if (!drag) return;
    cam.az -= 0.3 * (e.clientX - drag[0]);
    cam.el = Math.max(-89, Math.min(89, cam.el + 0.3 * (e.clientY - drag[1])));
    drag = [e.clientX, e.clientY];
  });
  canvas.addEventListener("wheel", (e) => { e.preventDefault(); cam.dist *= Math.exp(0.001 * e.deltaY); },
                          { passive: false });
  doc.addEventListener("keydown", (e) => {
    if (e.key === "r") { cam.az = cam0.azimuth_deg; cam.el = cam0.elevation_deg; cam.dist = cam0.distance; }
    if (e.key === " ") play.onclick();
  });
  syncUi();
  let fpsCount = 0, fpsT = performance.now(), fps = 0, mainMs = 0;
  const tick = (now) => {
    const t0 = performance.now();
    if (state.playing) {
      const elapsed = Math.max(0, now - state.t0); // rAF time may precede t0 slightly
      state.frame = (state.f0 + Math.floor(elapsed * header.fps / 1000)) % b.T;
      slider.value = String(state.frame);
    }
    const dpr = window.devicePixelRatio || 1;
    const w = Math.round(canvas.clientWidth * dpr), h = Math.round(canvas.clientHeight * dpr);
    if (canvas.width !== w || canvas.height !== h) { canvas.width = w; canvas.height = h; }
    const viewmat = orbitViewmat(cam0.center, cam.dist, cam.az, cam.el);
    const K = intrinsics(w, h, cam0.fov_deg);
    if (state.frame !== state.posedFrame) {
      renderer.setPose(poser.pose(state.frame));
      state.posedFrame = state.frame;
    }
    // re-sort when the centres may have moved in depth by more than a tenth of a 16-bit bin
    state.drift = poser.drift(viewmat, state.sorted);
    const tol = 0.1 * cam.dist / 65535;
    if (state.drift > tol && !state.pending) {
      const req = sorter.request(poser.verts32, poser.normals32, viewmat);
      if (req) state.pending = { id: req.id, verts: poser.verts32.slice(), normals: poser.normals32.slice(), viewmat };
    }
    renderer.draw(viewmat, K, state.white ? [1, 1, 1] : [0, 0, 0]);
    mainMs = performance.now() - t0;
    fpsCount++;
    if (now - fpsT > 500) { fps = 1000 * fpsCount / (now - fpsT); fpsCount = 0; fpsT = now; }
    info.textContent = `frame ${state.frame + 1}/${b.T}`;
    stats.textContent = `${fps.toFixed(0)} fps · ${b.N} Gaussians (${renderer.visible} drawn) · main ${mainMs.toFixed(1)} ms` +
      ` · sort ${state.sortMs.toFixed(1)} ms (${sorter.inWorker ? "worker" : "main thread"})` +
      ` · stale-sort depth drift ${state.drift === Infinity ? "-" : state.drift.toExponential(1)}`;
    // ready (for screenshots) once the drawn order belongs to the drawn pose and view
    if (state.sorted && state.drift <= tol) doc.body.dataset.ready = "1";
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
