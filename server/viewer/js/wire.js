// The live wire protocol in the page: the messages of protocol/messages.py and the frame header of
// protocol/frame.py, byte for byte (little-endian). Each WebSocket message carries one whole wire message
// (u32 length, u8 type, body). Pure functions: no DOM, so node can test them against the Python side.

export const PROTOCOL_VERSION = 1;
export const MessageType = { HELLO: 1, WELCOME: 2, POSE_UPDATE: 3, FRAME: 4, REFERENCE_REQUEST: 5, ERROR: 6, BYE: 7,
                             RECEIVE_REPORT: 8 };
export const MAX_REPORT_ENTRIES = 256;   // protocol/messages.py's bound on a ReceiveReport
export const ErrorCode = { PROTOCOL: 1, UNSUPPORTED_VERSION: 2, UNKNOWN_METHOD: 3, BAD_REQUEST: 4, UNAUTHORIZED: 5,
                           INTERNAL: 6 };
export const FATAL_CODES = [ErrorCode.UNSUPPORTED_VERSION, ErrorCode.UNKNOWN_METHOD, ErrorCode.BAD_REQUEST,
                            ErrorCode.UNAUTHORIZED];
export const Method = { QUASAR: 0, QUADSTREAM: 1, MESHWARP: 2, ATW: 3 };
export const FrameType = { REFERENCE: 0, RESIDUAL: 1 };

export class WireError extends Error {}

const utf8 = new TextEncoder();
const fromUtf8 = new TextDecoder("utf-8", { fatal: true });

function packString(s, name) {
  const b = utf8.encode(s);
  if (b.length > 0xffff) throw new WireError(`${name}: ${b.length} utf-8 bytes exceeds the limit of 65535`);
  return b;
}

function message(type, bodyLength, fill) {
  const buf = new ArrayBuffer(5 + bodyLength);
  const view = new DataView(buf);
  view.setUint32(0, 1 + bodyLength, true);
  view.setUint8(4, type);
  fill(view, new Uint8Array(buf), 5);
  return buf;
}

function finite(name, values) {
  for (const v of values) {
    if (typeof v !== "number" || !Number.isFinite(v)) throw new WireError(`${name}: expected finite numbers, got ${values}`);
  }
}

export function encodeHello({ version = PROTOCOL_VERSION, method, width, height, fovyDeg, token = "" }) {
  if (!(Number.isInteger(width) && width > 0 && Number.isInteger(height) && height > 0)) {
    throw new WireError(`Hello size: expected positive integers, got ${width}x${height}`);
  }
  if (!(fovyDeg > 0 && fovyDeg < 180)) throw new WireError(`Hello.fovy_deg: expected 0 < fovy < 180, got ${fovyDeg}`);
  const m = packString(method, "Hello.method"), t = packString(token, "Hello.token");
  return message(MessageType.HELLO, 18 + 2 + m.length + 2 + t.length, (view, bytes, o) => {
    view.setUint16(o, version, true);
    view.setUint32(o + 2, width, true);
    view.setUint32(o + 6, height, true);
    view.setFloat64(o + 10, fovyDeg, true);
    view.setUint16(o + 18, m.length, true);
    bytes.set(m, o + 20);
    view.setUint16(o + 20 + m.length, t.length, true);
    bytes.set(t, o + 22 + m.length);
  });
}

export const MAX_GAZE_DEG = 89;   // quadcast.protocol.pose.MAX_GAZE_DEG

// `gaze`: where the viewer looks, [x, y] degrees to the right and up from the view axis (each within +-89), or null:
// a pose without one (72 bytes), as the Python client sends without --gaze.
export function encodePoseUpdate(seq, tClient, position, quat, gaze = null) {
  finite("PoseUpdate", [tClient, ...position, ...quat]);
  if (quat.reduce((a, q) => a + q * q, 0) < 1e-12) throw new WireError("PoseUpdate.quat: expected a non-zero quaternion");
  if (gaze !== null) {
    finite("PoseUpdate.gaze", gaze);
    if (gaze.length !== 2 || !gaze.every((g) => Math.abs(g) < MAX_GAZE_DEG)) {
      throw new WireError(`PoseUpdate.gaze: expected two angles within +-${MAX_GAZE_DEG} degrees of the view axis, got ${gaze}`);
    }
  }
  return message(MessageType.POSE_UPDATE, gaze === null ? 72 : 88, (view, bytes, o) => {
    view.setBigUint64(o, BigInt(seq), true);
    view.setFloat64(o + 8, tClient, true);
    [...position, ...quat, ...(gaze ?? [])].forEach((v, i) => view.setFloat64(o + 16 + 8 * i, v, true));
  });
}

export function encodeReferenceRequest(reason = "") {
  const r = packString(reason, "ReferenceRequest.reason");
  return message(MessageType.REFERENCE_REQUEST, 2 + r.length, (view, bytes, o) => {
    view.setUint16(o, r.length, true);
    bytes.set(r, o + 2);
  });
}

export function encodeBye() {
  return message(MessageType.BYE, 0, () => {});
}

// ReceiveReport: when each frame arrived and how big it was, [[frameId, bytes, tArrive], ...] (tArrive on the clock
// the page's poses carry), for the server's rate controller; [] says "this client reports arrivals".
export function encodeReceiveReport(entries) {
  if (entries.length > MAX_REPORT_ENTRIES) {
    throw new WireError(`ReceiveReport.count: ${entries.length} entries, at most ${MAX_REPORT_ENTRIES}`);
  }
  entries.forEach(([frameId, bytes, tArrive], i) => {
    for (const [name, v] of [["frame_id", frameId], ["bytes", bytes]]) {
      if (!(Number.isInteger(v) && v >= 0 && v <= 0xffffffff)) {
        throw new WireError(`ReceiveReport.entries[${i}].${name}: expected an integer in [0, 2^32), got ${v}`);
      }
    }
    finite(`ReceiveReport.entries[${i}].t_arrive`, [tArrive]);
  });
  return message(MessageType.RECEIVE_REPORT, 2 + 16 * entries.length, (view, bytes, o) => {
    view.setUint16(o, entries.length, true);
    entries.forEach(([frameId, size, tArrive], i) => {
      view.setUint32(o + 2 + 16 * i, frameId, true);
      view.setUint32(o + 6 + 16 * i, size, true);
      view.setFloat64(o + 10 + 16 * i, tArrive, true);
    });
  });
}

function readString(view, pos, what) {
  if (pos + 2 > view.byteLength) throw new WireError(`${what}: body truncated reading its length`);
  const n = view.getUint16(pos, true);
  if (pos + 2 + n > view.byteLength) throw new WireError(`${what}: says ${n} bytes, only ${view.byteLength - pos - 2} remain`);
  try {
    return [fromUtf8.decode(new Uint8Array(view.buffer, view.byteOffset + pos + 2, n)), pos + 2 + n];
  } catch (e) {
    throw new WireError(`${what}: invalid utf-8`);
  }
}

// One wire message (an ArrayBuffer holding exactly one) -> {type, ...fields}. Frame keeps its payload bytes.
export function decodeMessage(buffer) {
  if (buffer.byteLength < 5) throw new WireError(`message: ${buffer.byteLength} bytes, shorter than its prefix`);
  const view = new DataView(buffer);
  const length = view.getUint32(0, true);
  if (length !== buffer.byteLength - 4) {
    throw new WireError(`message length: prefix says ${length} bytes, the WebSocket message has ${buffer.byteLength - 4}`);
  }
  const type = view.getUint8(4);
  const body = new DataView(buffer, 5);
  const need = (n, name) => {
    if (body.byteLength !== n) throw new WireError(`${name}: body of ${body.byteLength} bytes, expected ${n}`);
  };
  switch (type) {
    case MessageType.WELCOME:
      need(16, "Welcome");
      return { type, sessionId: Number(body.getBigUint64(0, true)), serverHz: body.getFloat64(8, true) };
    case MessageType.FRAME:
      return { type, payload: new Uint8Array(buffer, 5) };
    case MessageType.ERROR: {
      if (body.byteLength < 2) throw new WireError("ErrorMessage: body truncated");
      const code = body.getUint16(0, true);
      const [text, end] = readString(body, 2, "ErrorMessage.text");
      if (end !== body.byteLength) throw new WireError("ErrorMessage: unexpected trailing bytes");
      return { type, code, text };
    }
    case MessageType.BYE:
      need(0, "Bye");
      return { type };
    default:
      throw new WireError(`message type: ${type} is not one the server sends`);
  }
}

// protocol/frame.py's header: magic, version, method, type | self-contained << 7, frame id, reference id, t,
// position (3 f8), quat (4 f8), video length, geometry length.
export const FRAME_MAGIC = "QDCF";
export const FRAME_VERSION = 2;
export const FRAME_HEADER_BYTES = 88;

// The frame id in a frame payload's fixed header, before the payload is checked (protocol/frame.py's
// peek_frame_id): what the page reports the moment a frame arrives.
export function peekFrameId(bytes) {
  if (bytes.byteLength < 12) throw new WireError(`frame payload: ${bytes.byteLength} bytes, too short for a frame id`);
  return new DataView(bytes.buffer, bytes.byteOffset, bytes.byteLength).getUint32(8, true);
}

export function decodeFramePayload(bytes) {
  if (bytes.byteLength < FRAME_HEADER_BYTES) {
    throw new WireError(`frame payload: truncated header (${bytes.byteLength} of ${FRAME_HEADER_BYTES} bytes)`);
  }
  const view = new DataView(bytes.buffer, bytes.byteOffset, bytes.byteLength);
  const magic = String.fromCharCode(...bytes.subarray(0, 4));
  if (magic !== FRAME_MAGIC) throw new WireError(`frame payload: bad magic ${JSON.stringify(magic)}`);
  const version = view.getUint16(4, true);
  if (version !== FRAME_VERSION) throw new WireError(`frame payload: version ${version} is not supported (expected ${FRAME_VERSION})`);
  const method = view.getUint8(6), kind = view.getUint8(7);
  const frameType = kind & 0x7f;
  if (frameType > FrameType.RESIDUAL) throw new WireError(`frame payload: unknown frame type ${frameType}`);
  const f64 = (o) => view.getFloat64(o, true);
  const position = [f64(24), f64(32), f64(40)];
  const quat = [f64(48), f64(56), f64(64), f64(72)];
  const t = f64(16);
  if (![t, ...position, ...quat].every(Number.isFinite) || quat.reduce((a, q) => a + q * q, 0) < 1e-12) {
    throw new WireError("frame payload: non-finite time/pose or zero quaternion");
  }
  const nVideo = view.getUint32(80, true), nGeometry = view.getUint32(84, true);
  if (FRAME_HEADER_BYTES + nVideo + nGeometry !== bytes.byteLength) {
    throw new WireError(`frame payload: header says ${nVideo} video + ${nGeometry} geometry bytes, message has ${bytes.byteLength - FRAME_HEADER_BYTES}`);
  }
  return {
    method, frameType, selfContained: (kind & 0x80) !== 0,
    frameId: view.getUint32(8, true), referenceId: view.getUint32(12, true), t, position, quat,
    video: bytes.subarray(FRAME_HEADER_BYTES, FRAME_HEADER_BYTES + nVideo),
    geometry: bytes.subarray(FRAME_HEADER_BYTES + nVideo),
  };
}
