// CPU reference of the player's GPU posing and of its depth keys, for the tests only (the shipped
// page does not need it): poseMesh (face and vertex passes), poseGaussians (the placement of the page's
// per-Gaussian pass), gaussianDepths (the worker's sort keys, one per Gaussian), sortDepths and sortByDepth
// (a counting sort of given depths), keyVisibilities (the key light's visibility that pass reads). They mirror meshsplat.mesh.geometry, meshsplat.embedding and
// meshsplat.gaussians.compose; tests/test_viewer.py compares them with those under Node.
import { EPS, EXACT_KEY_MAX, NEAR_PLANE, faceGeometry, frameVertices, keyShadowMap, keyVisibility, vertexKeys }
  from "../../src/meshsplat/viewer/static/viewer.js";

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

/**
 * Sort key [N] (Float32Array) of every posed Gaussian: the camera depth of its centre, Phong point
 * + d * normalized interpolated normal, as the vertex shader computes it; per-vertex camera depths
 * make it z = sum w z_v + d (sum w r3.n_v) / |sum w n_v|. Above EXACT_KEY_MAX Gaussians the
 * division by |sum w n_v| is skipped: the key then differs from the centre's depth by at most
 * |d| (1/|n_interp| - 1) (zero for d = 0 or equal corner normals; see docs/viewer.md).
 * From the posed vertices `verts` and unit vertex normals `normals` (both [V*3]); `g` holds face,
 * uv, d of the Gaussians and the mesh faces (a decoded bundle or the worker's copy), and caches the
 * Gaussians' corner vertices. Returns {lo, hi} (visible key range, for sortDepths) and `moved`,
 * the largest |key - prev| when `prev` [N] is given (else Infinity). sortGaussians computes the
 * same keys inside its counting sort.
 */
export function gaussianDepths(g, verts, normals, viewmat, depth, prev) {
  const N = g.N, uv = g.uv, dd = g.d;
  const exact = N <= EXACT_KEY_MAX;
  depth = depth || new Float32Array(N);
  const { pv, cn } = vertexKeys(g, verts, normals, viewmat, exact);
  let lo = Infinity, hi = -Infinity, moved = 0;
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
    depth[i] = u * pv[a] + v * pv[b] + w * pv[c] + s * (u * pv[a + 1] + v * pv[b + 1] + w * pv[c + 1]);
    const z = depth[i]; // the stored float32 value
    if (z >= NEAR_PLANE) { if (z < lo) lo = z; if (z > hi) hi = z; }
    if (prev) { const m = Math.abs(z - prev[i]); if (m > moved) moved = m; }
  }
  return { depth, lo, hi, moved: prev ? moved : Infinity };
}

/**
 * Back-to-front order of the depths >= the near plane: one counting sort on 16-bit quantized depth
 * over the visible range [lo, hi] (computed when not given; ties keep index order). Fills `order`
 * [n]; returns the visible count. `ws` (optional) holds reusable scratch
 * {counts: Uint32Array(65536), bins: Uint16Array(n)}.
 */
export function sortDepths(depth, n, order, ws, lo, hi) {
  if (lo === undefined) {
    lo = Infinity; hi = -Infinity;
    for (let g = 0; g < n; g++) {
      const z = depth[g];
      if (z >= NEAR_PLANE) { if (z < lo) lo = z; if (z > hi) hi = z; }
    }
  }
  const counts = ws && ws.counts ? ws.counts : new Uint32Array(65536);
  const bins = ws && ws.bins && ws.bins.length >= n ? ws.bins : new Uint16Array(n);
  counts.fill(0);
  const q = hi > lo ? 65535 / (hi - lo) : 0;
  let visible = 0;
  for (let g = 0; g < n; g++) {
    const z = depth[g];
    if (!(z >= NEAR_PLANE)) continue;
    const bin = 65535 - Math.min(65535, ((z - lo) * q) | 0); // far first; 0 <= (z - lo) q <= 65535
    bins[g] = bin; counts[bin]++; visible++;
  }
  for (let i = 1; i < 65536; i++) counts[i] += counts[i - 1];
  for (let g = n - 1; g >= 0; g--) if (depth[g] >= NEAR_PLANE) order[--counts[bins[g]]] = g;
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

/**
 * Visibility [N] (0 or 1; a soft key: the mean over its maps) from the key light (header.shading.key) of
 * every Gaussian's surface point (Phong point at its uv, before d) in frame `t`: the page's height maps
 * (keyShadowMap of the float32 vertices it uploads) and the splat shader's lookup with the Phong normal's
 * bias (keyVisibility).
 */
export function keyVisibilities(b, t) {
  const p = Float32Array.from(frameVertices(b, t)), f = b.faces, N = b.N;
  const map = keyShadowMap(f, b.V, p, b.header.shading.key);
  const nrm = poseMesh(b, Float64Array.from(p)).normals, out = new Float64Array(N), x = [0, 0, 0], n = [0, 0, 0];
  for (let i = 0; i < N; i++) {
    const u = b.uv[2 * i], v = b.uv[2 * i + 1], w = 1 - u - v, k = 3 * b.face[i];
    const ia = 3 * f[k], ib = 3 * f[k + 1], ic = 3 * f[k + 2];
    for (let j = 0; j < 3; j++) {
      x[j] = u * p[ia + j] + v * p[ib + j] + w * p[ic + j];
      n[j] = u * nrm[ia + j] + v * nrm[ib + j] + w * nrm[ic + j];
    }
    const r = 1 / Math.sqrt(Math.max(n[0] ** 2 + n[1] ** 2 + n[2] ** 2, 1e-24));
    out[i] = keyVisibility(map, x, [n[0] * r, n[1] * r, n[2] * r]);
  }
  return { visible: Array.from(out), empty: Array.from(map.depth).filter((d) => d === -Infinity).length };
}
