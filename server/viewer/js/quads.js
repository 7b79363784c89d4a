// Quad blobs (protocol/quads.py, version 3) in the page: header, per-layer headers, one zstd frame of columns
// stored as byte planes (words, theta codes, phi codes, depths, float16 offsets). Decoded straight into the
// rows the mesh shader reads (render/quadmesh.py's quads_to_gpu): 24 floats per quad --
// x, y, size_log2, 0, normal xyz, depth, 16 depth offsets (0 for flattened quads).
// Every defect throws a QuadBlobError naming it, as decode_quad_frame raises ProtocolError.
import { decompress } from "../node_modules/fzstd/esm/index.mjs";

export const BLOB_MAGIC = "QDCQ";
export const BLOB_VERSION = 3;
export const HEADER_BYTES = 12;       // <4sHBBI
export const LAYER_BYTES = 85;        // <BHH4H16fII
export const MAX_LAYERS = 16;
export const MAX_SIZE_LOG2 = 11;
export const ROW_FLOATS = 24;
export const LayerKind = { VISIBLE: 0, HIDDEN: 1, WIDE: 2, UPDATED: 3, REVEALED: 4, FAR: 5 };
const QUAD_BYTES = 10, OFFSET_ROW_BYTES = 32;

export class QuadBlobError extends Error {}

// float16 bits -> float32, as a table (65536 entries, made once)
const HALF = (() => {
  const table = new Float32Array(65536);
  for (let h = 0; h < 65536; h++) {
    const sign = h & 0x8000 ? -1 : 1, exp = (h >> 10) & 0x1f, frac = h & 0x3ff;
    table[h] = exp === 0 ? sign * frac * 2 ** -24
      : exp === 31 ? (frac ? NaN : sign * Infinity)
      : sign * (1 + frac / 1024) * 2 ** (exp - 15);
  }
  return table;
})();

// unit normals of the two uint8 angle codes (protocol/quads.py unpack_normals), made once
const THETA_STEPS = 255, PHI_STEPS = 256;

export function decodeQuadBlob(bytes, { maxQuads = 1 << 23 } = {}) {
  if (bytes.byteLength < HEADER_BYTES) throw new QuadBlobError(`truncated blob: header needs ${HEADER_BYTES} bytes, got ${bytes.byteLength}`);
  const view = new DataView(bytes.buffer, bytes.byteOffset, bytes.byteLength);
  const magic = String.fromCharCode(...bytes.subarray(0, 4));
  if (magic !== BLOB_MAGIC) throw new QuadBlobError(`header.magic: expected ${BLOB_MAGIC}, got ${JSON.stringify(magic)}`);
  const version = view.getUint16(4, true);
  if (version !== BLOB_VERSION) throw new QuadBlobError(`header.version: expected ${BLOB_VERSION}, got ${version}`);
  if (view.getUint8(6) !== 0) throw new QuadBlobError(`header.flags: expected 0, got ${view.getUint8(6)}`);
  const layerCount = view.getUint8(7);
  if (layerCount > MAX_LAYERS) throw new QuadBlobError(`header.layer_count: expected at most ${MAX_LAYERS}, got ${layerCount}`);
  const payloadSize = view.getUint32(8, true);
  const layersEnd = HEADER_BYTES + layerCount * LAYER_BYTES;
  if (bytes.byteLength < layersEnd) throw new QuadBlobError(`truncated blob: ${layerCount} layer headers need ${layersEnd} bytes, got ${bytes.byteLength}`);

  const layers = [];
  let totalQuads = 0, totalOffsets = 0;
  for (let i = 0; i < layerCount; i++) {
    const o = HEADER_BYTES + i * LAYER_BYTES;
    const kind = view.getUint8(o), width = view.getUint16(o + 1, true), height = view.getUint16(o + 3, true);
    const rect = [0, 1, 2, 3].map((k) => view.getUint16(o + 5 + 2 * k, true));
    const camera = new Float32Array(16);
    for (let k = 0; k < 16; k++) camera[k] = view.getFloat32(o + 13 + 4 * k, true);
    const count = view.getUint32(o + 77, true), offsetCount = view.getUint32(o + 81, true);
    if (kind > LayerKind.FAR) throw new QuadBlobError(`layer[${i}].kind: unknown kind ${kind}`);
    if (!width || !height) throw new QuadBlobError(`layer[${i}]: expected a non-empty image, got ${width}x${height}`);
    if (offsetCount > count) throw new QuadBlobError(`layer[${i}].offset_count: expected <= quad count ${count}, got ${offsetCount}`);
    if (!camera.every(Number.isFinite)) throw new QuadBlobError(`layer[${i}].camera: expected finite numbers`);
    totalQuads += count;
    totalOffsets += offsetCount;
    if (totalQuads > maxQuads) throw new QuadBlobError(`layer[${i}].quad_count: total quads ${totalQuads} exceeds max_quads ${maxQuads}`);
    layers.push({ kind, width, height, rect, camera, count, offsetCount, rows: null });
  }
  const expected = totalQuads * QUAD_BYTES + totalOffsets * OFFSET_ROW_BYTES;
  if (payloadSize !== expected) throw new QuadBlobError(`header.payload_size: expected ${expected} (from layer counts), got ${payloadSize}`);

  let raw;
  if (expected === 0) {
    raw = new Uint8Array(0);
  } else {
    try {
      raw = decompress(bytes.subarray(layersEnd), new Uint8Array(expected));
    } catch (e) {
      throw new QuadBlobError(`payload: not a valid zstd frame (${e.message || e})`);
    }
    if (raw.byteLength !== expected) throw new QuadBlobError(`payload: decompressed to ${raw.byteLength} bytes, expected ${expected}`);
  }

  // column starts (byte planes: plane b of a column of n items is raw[start + b*n ... + n])
  const n = totalQuads, nOff = totalOffsets * 16;
  const words = 0, theta = 4 * n, phi = 5 * n, depth = 6 * n, offsets = 10 * n;
  const f32 = new Float32Array(1), u32 = new Uint32Array(f32.buffer);
  let q = 0, offRow = 0;
  for (const [i, layer] of layers.entries()) {
    const rows = new Float32Array(layer.count * ROW_FLOATS);
    let nonFlattened = 0;
    for (let k = 0; k < layer.count; k++, q++) {
      const w = (raw[words + q] | (raw[words + n + q] << 8) | (raw[words + 2 * n + q] << 16) | (raw[words + 3 * n + q] << 24)) >>> 0;
      const x = (w >>> 12) & 0xfff, y = w & 0xfff, sizeLog2 = (w >>> 24) & 0x3f, flattened = (w >>> 31) !== 0;
      if (sizeLog2 > MAX_SIZE_LOG2) throw new QuadBlobError(`layer[${i}].quads.size_log2[${k}]: expected 0..${MAX_SIZE_LOG2}, got ${sizeLog2}`);
      if (x >= layer.width || y >= layer.height) throw new QuadBlobError(`layer[${i}].quads[${k}]: (${x}, ${y}) outside the ${layer.width}x${layer.height} layer`);
      u32[0] = (raw[depth + q] | (raw[depth + n + q] << 8) | (raw[depth + 2 * n + q] << 16) | (raw[depth + 3 * n + q] << 24)) >>> 0;
      const d = f32[0];
      if (!Number.isFinite(d)) throw new QuadBlobError(`layer[${i}].quads.depth[${k}]: expected finite, got ${d}`);
      const t = raw[theta + q] * (Math.PI / THETA_STEPS), p = raw[phi + q] * (2 * Math.PI / PHI_STEPS) - Math.PI;
      const r = k * ROW_FLOATS;
      rows[r] = x; rows[r + 1] = y; rows[r + 2] = sizeLog2;
      rows[r + 4] = Math.sin(t) * Math.cos(p); rows[r + 5] = Math.sin(t) * Math.sin(p); rows[r + 6] = Math.cos(t);
      rows[r + 7] = d;
      if (!flattened) {
        if (offRow >= totalOffsets) throw new QuadBlobError(`layer[${i}].offset_count: more non-flattened quads than offset rows`);
        for (let c = 0; c < 16; c++) {
          const item = offRow * 16 + c;
          const v = HALF[raw[offsets + item] | (raw[offsets + nOff + item] << 8)];
          if (!Number.isFinite(v)) throw new QuadBlobError(`layer[${i}].quads.offsets[${nonFlattened},${c}]: expected a finite float16`);
          rows[r + 8 + c] = v;
        }
        offRow++;
        nonFlattened++;
      }
    }
    if (nonFlattened !== layer.offsetCount) {
      throw new QuadBlobError(`layer[${i}].offset_count: expected ${nonFlattened} (non-flattened quads), got ${layer.offsetCount}`);
    }
    layer.rows = rows;
  }
  return { layers };
}

// A layer camera's 16 floats (render/camera.py Camera.to_array): position, xyzw quaternion, frustum l r b t n f.
export function layerCamera(values) {
  const position = [values[0], values[1], values[2]];
  const quat = [values[3], values[4], values[5], values[6]];
  const [left, right, bottom, top, near, far] = Array.from(values.subarray(7, 13));
  const norm = Math.hypot(...quat);
  if (!(norm > 1e-9) || !(near > 0 && near < far) || !(left < right && bottom < top)) {
    throw new QuadBlobError(`layer camera: invalid pose or frustum ${Array.from(values.subarray(0, 13))}`);
  }
  return { position, quat: quat.map((v) => v / norm), frustum: { left, right, bottom, top, near, far } };
}
