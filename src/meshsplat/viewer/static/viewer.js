// meshsplat WebGL2 viewer: poses mesh-embedded Gaussians on the CPU every frame and splats them.
//
// Pure functions (decodeBundle, frameVertices, poseMesh, poseGaussians, orbitViewmat, intrinsics)
// mirror meshsplat.mesh.geometry / meshsplat.embedding / meshsplat.gaussians.compose exactly and run
// under Node for the tests. The UI starts only in a page that holds the embedded avatar data.
// Cameras follow the project convention: world->camera viewmat in OpenCV axes (x right, y down,
// z forward), pinhole K, pixel centres at +0.5. Matrices are row-major flat arrays.

export const SH_C0 = 0.28209479177387814;
const EPS = 1e-12;            // meshsplat.mesh.geometry._EPS
const EPS2D = 0.3;            // 2D covariance dilation (pixels^2), as the rasterizer
const ALPHA_THRESHOLD = 1 / 255;
const ALPHA_MAX = 0.999;
const MAX_EXTEND = 3.33;
const FOV_CLAMP_MARGIN = 0.3;
const NEAR_PLANE = 0.01;

// ------------------------------------------------------------------ bundle decoding
const TYPED = { float32: Float32Array, uint32: Uint32Array, int16: Int16Array };

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
  const b = {
    header, V: header.num_vertices, F: header.num_faces, N: header.num_gaussians, T: header.num_frames,
    faces: arr.faces, cano: arr.canonical_vertices, frames: arr.frames,
    face: arr.gaussian_face, uv: arr.gaussian_uv, d: arr.gaussian_d, rot: arr.gaussian_rotation,
    scale: arr.gaussian_scale, opacity: arr.gaussian_opacity, rgb: arr.gaussian_rgb,
  };
  // canonical per-face frames (constant) and areas
  const cf = faceGeometry(b, Float64Array.from(b.cano));
  b.canoFrames = cf.frames;
  b.canoAreas = cf.areas;
  return b;
}

/** Vertices [V*3] (Float64Array) of frame `t`, dequantized when stored as int16. */
export function frameVertices(b, t, out) {
  const n = b.V * 3, base = t * n;
  out = out || new Float64Array(n);
  if (b.header.vertex_encoding === "int16") {
    const o = b.header.vertex_offset, s = b.header.vertex_step;
    for (let i = 0; i < n; i++) out[i] = o[i % 3] + b.frames[base + i] * s[i % 3];
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

/** Posed per-vertex normals [V*3], quaternions [V*4] (wxyz) and per-face area ratios [F]. */
export function poseMesh(b, p) {
  const V = b.V, F = b.F, f = b.faces;
  const g = faceGeometry(b, p);
  const rot = new Float64Array(9), qf = new Float64Array(F * 4), ratio = new Float64Array(F);
  const cf = b.canoFrames, pf = g.frames;
  for (let k = 0; k < F; k++) {
    const o = 9 * k;
    for (let i = 0; i < 3; i++) for (let j = 0; j < 3; j++) // R = F_posed F_cano^T
      rot[3 * i + j] = pf[o + 3 * i] * cf[o + 3 * j] + pf[o + 3 * i + 1] * cf[o + 3 * j + 1] + pf[o + 3 * i + 2] * cf[o + 3 * j + 2];
    matrixToQuat(rot, 0, qf, 4 * k);
    const a0 = b.canoAreas[k];
    ratio[k] = a0 > EPS ? g.areas[k] / a0 : 1;
  }
  // area-weighted vertex normals (sum of cross products) and reference face per vertex
  const nrm = new Float64Array(V * 3), wmax = new Float64Array(V).fill(-1), ref = new Int32Array(V);
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
  const acc = new Float64Array(V * 4);
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
  return { normals: nrm, quats: acc, areaRatio: ratio };
}

// ------------------------------------------------------------------ Gaussians
/**
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

/** Back-to-front order of the Gaussians in front of the camera: counting sort on 16-bit depth. */
export function sortByDepth(means, n, viewmat, order, counts) {
  const depth = new Float32Array(n);
  let lo = Infinity, hi = -Infinity;
  const r0 = viewmat[8], r1 = viewmat[9], r2 = viewmat[10], t = viewmat[11];
  for (let g = 0; g < n; g++) {
    depth[g] = r0 * means[3 * g] + r1 * means[3 * g + 1] + r2 * means[3 * g + 2] + t;
    const z = depth[g]; // the stored float32 value, so that lo <= z <= hi below
    if (z >= NEAR_PLANE) { if (z < lo) lo = z; if (z > hi) hi = z; }
  }
  counts = counts || new Uint32Array(65536);
  counts.fill(0);
  const bins = new Uint16Array(n), q = hi > lo ? 65535 / (hi - lo) : 0;
  let visible = 0;
  for (let g = 0; g < n; g++) {
    if (!(depth[g] >= NEAR_PLANE)) continue;
    const bin = 65535 - Math.max(0, Math.min(65535, Math.floor((depth[g] - lo) * q))); // far first
    bins[g] = bin; counts[bin]++; visible++;
  }
  for (let i = 1; i < 65536; i++) counts[i] += counts[i - 1];
  order = order || new Uint32Array(n);
  for (let g = n - 1; g >= 0; g--) if (depth[g] >= NEAR_PLANE) order[--counts[bins[g]]] = g;
  return visible;
}

// ------------------------------------------------------------------ WebGL2 splatting
const VERT = `#version 300 es
precision highp float;
layout(location=0) in vec2 corner;      // quad corner in {-1, 1}^2
layout(location=1) in vec3 mean;
layout(location=2) in vec3 covA;        // xx, xy, xz
layout(location=3) in vec3 covB;        // yy, yz, zz
layout(location=4) in vec4 rgba;        // colour, opacity
uniform mat3 R; uniform vec3 tr;        // world->camera (OpenCV)
uniform vec4 K;                         // fx, fy, cx, cy
uniform vec2 size;                      // width, height (pixels)
out vec2 offs; out vec3 conic; out vec4 col;
void main() {
  vec3 mc = R * mean + tr;
  if (mc.z < ${NEAR_PLANE}) { gl_Position = vec4(0.0, 0.0, 2.0, 1.0); return; }
  mat3 S = mat3(covA.x, covA.y, covA.z, covA.y, covB.x, covB.y, covA.z, covB.y, covB.z);
  mat3 C = R * S * transpose(R);
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
  float op = rgba.a;
  if (det <= 0.0 || op < ${ALPHA_THRESHOLD}) { gl_Position = vec4(0.0, 0.0, 2.0, 1.0); return; }
  conic = vec3(c, -b, a) / det;
  float extend = min(${MAX_EXTEND}, sqrt(2.0 * log(op / ${ALPHA_THRESHOLD})));
  vec2 radius = ceil(extend * sqrt(vec2(a, c)));
  vec2 m2 = K.xy * mc.xy * rz + K.zw;   // pixel position, y down
  offs = corner * radius;
  vec2 px = m2 + offs;
  gl_Position = vec4(2.0 * px.x / size.x - 1.0, 1.0 - 2.0 * px.y / size.y, 0.0, 1.0);
  col = rgba;
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

/** Splat renderer on a WebGL2 canvas; `draw(posed, viewmat, K, background)`. */
export class SplatRenderer {
  constructor(canvas, bundle) {
    const gl = canvas.getContext("webgl2", { antialias: false, premultipliedAlpha: false, preserveDrawingBuffer: true });
    if (!gl) throw new Error("WebGL2 is not available in this browser");
    this.gl = gl; this.b = bundle;
    const prog = gl.createProgram();
    gl.attachShader(prog, compile(gl, gl.VERTEX_SHADER, VERT));
    gl.attachShader(prog, compile(gl, gl.FRAGMENT_SHADER, FRAG));
    gl.linkProgram(prog);
    if (!gl.getProgramParameter(prog, gl.LINK_STATUS)) throw new Error(gl.getProgramInfoLog(prog));
    this.prog = prog;
    this.loc = Object.fromEntries(["R", "tr", "K", "size"].map((n) => [n, gl.getUniformLocation(prog, n)]));
    this.vao = gl.createVertexArray();
    gl.bindVertexArray(this.vao);
    const quad = gl.createBuffer();
    gl.bindBuffer(gl.ARRAY_BUFFER, quad);
    gl.bufferData(gl.ARRAY_BUFFER, new Float32Array([-1, -1, 1, -1, -1, 1, 1, 1]), gl.STATIC_DRAW);
    gl.enableVertexAttribArray(0);
    gl.vertexAttribPointer(0, 2, gl.FLOAT, false, 0, 0);
    this.inst = gl.createBuffer();
    gl.bindBuffer(gl.ARRAY_BUFFER, this.inst);
    const stride = 13 * 4;
    [[1, 3, 0], [2, 3, 3], [3, 3, 6], [4, 4, 9]].forEach(([loc, n, off]) => {
      gl.enableVertexAttribArray(loc);
      gl.vertexAttribPointer(loc, n, gl.FLOAT, false, stride, off * 4);
      gl.vertexAttribDivisor(loc, 1);
    });
    this.data = new Float32Array(bundle.N * 13);
    gl.bufferData(gl.ARRAY_BUFFER, this.data.byteLength, gl.DYNAMIC_DRAW);
    this.order = new Uint32Array(bundle.N);
    this.counts = new Uint32Array(65536);
    this.visible = 0;
  }

  /** Depth-sort `posed` for `viewmat` and upload the instance data in back-to-front order. */
  upload(posed, viewmat) {
    const b = this.b, gl = this.gl, data = this.data, order = this.order;
    const n = sortByDepth(posed.means, b.N, viewmat, order, this.counts);
    for (let i = 0; i < n; i++) {
      const g = order[i], o = 13 * i;
      data[o] = posed.means[3 * g]; data[o + 1] = posed.means[3 * g + 1]; data[o + 2] = posed.means[3 * g + 2];
      for (let j = 0; j < 6; j++) data[o + 3 + j] = posed.cov[6 * g + j];
      data[o + 9] = b.rgb[3 * g]; data[o + 10] = b.rgb[3 * g + 1]; data[o + 11] = b.rgb[3 * g + 2];
      data[o + 12] = b.opacity[g];
    }
    gl.bindBuffer(gl.ARRAY_BUFFER, this.inst);
    gl.bufferSubData(gl.ARRAY_BUFFER, 0, data, 0, n * 13);
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
    gl.bindVertexArray(this.vao);
    gl.drawArraysInstanced(gl.TRIANGLE_STRIP, 0, 4, this.visible);
  }
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
  const cam0 = header.camera;
  const cam = { az: cam0.azimuth_deg, el: cam0.elevation_deg, dist: cam0.distance };
  const state = {
    frame: Math.min(Math.max(parseInt(params.get("frame") || "0", 10) || 0, 0), b.T - 1),
    playing: params.get("frame") === null && params.get("play") !== "0" && b.T > 1,
    white: (params.get("bg") || header.background || "white") !== "black",
    posedFrame: -1, posed: null, dirty: true, t0: performance.now(), f0: 0,
  };
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
    drag = [e.clientX, e.clientY]; state.dirty = true;
  });
  canvas.addEventListener("wheel", (e) => { e.preventDefault(); cam.dist *= Math.exp(0.001 * e.deltaY); state.dirty = true; },
                          { passive: false });
  doc.addEventListener("keydown", (e) => {
    if (e.key === "r") { cam.az = cam0.azimuth_deg; cam.el = cam0.elevation_deg; cam.dist = cam0.distance; state.dirty = true; }
    if (e.key === " ") play.onclick();
  });
  syncUi();
  let fpsCount = 0, fpsT = performance.now(), fps = 0, poseMs = 0, sortMs = 0;
  const tick = (now) => {
    if (state.playing) {
      const elapsed = Math.max(0, now - state.t0); // rAF time may precede t0 slightly
      state.frame = (state.f0 + Math.floor(elapsed * header.fps / 1000)) % b.T;
      slider.value = String(state.frame);
    }
    const dpr = window.devicePixelRatio || 1;
    const w = Math.round(canvas.clientWidth * dpr), h = Math.round(canvas.clientHeight * dpr);
    if (canvas.width !== w || canvas.height !== h) { canvas.width = w; canvas.height = h; state.dirty = true; }
    const viewmat = orbitViewmat(cam0.center, cam.dist, cam.az, cam.el);
    const K = intrinsics(w, h, cam0.fov_deg);
    if (state.posed === null || state.frame !== state.posedFrame) {
      const t = performance.now();
      state.posed = poseGaussians(b, state.frame, null, state.posed);
      state.posedFrame = state.frame; state.dirty = true;
      poseMs = performance.now() - t;
    }
    if (state.dirty) {
      const t = performance.now();
      renderer.upload(state.posed, viewmat);
      sortMs = performance.now() - t;
      state.dirty = false;
    }
    renderer.draw(viewmat, K, state.white ? [1, 1, 1] : [0, 0, 0]);
    fpsCount++;
    if (now - fpsT > 500) { fps = 1000 * fpsCount / (now - fpsT); fpsCount = 0; fpsT = now; }
    info.textContent = `frame ${state.frame + 1}/${b.T}`;
    stats.textContent = `${fps.toFixed(0)} fps · ${b.N} Gaussians (${renderer.visible} drawn) · pose ${poseMs.toFixed(1)} ms · sort ${sortMs.toFixed(1)} ms`;
    doc.body.dataset.ready = "1";
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
