// Runs the viewer page's pure modules (server/viewer/js) under node for tests/test_viewer_js.py: reads a JSON
// request file (argv[2]), writes a JSON answer to stdout. Byte strings travel as base64.
import { readFileSync } from "node:fs";
import { decodeQuadBlob, layerCamera } from "../server/viewer/js/quads.js";
import { QuadCache } from "../server/viewer/js/cache.js";
import { ClientSession } from "../server/viewer/js/session.js";
import { codecString, isIdr } from "../server/viewer/js/video.js";
import { gazeAt, parseQuasarTrace, tracePoseAt, viewMatrix, projection, symmetricFrustum, quatFromYawPitch } from "../server/viewer/js/math.js";
import * as wire from "../server/viewer/js/wire.js";

const req = JSON.parse(readFileSync(process.argv[2], "utf8"));
const bytes = (b64) => new Uint8Array(Buffer.from(b64, "base64"));
const b64 = (buf) => Buffer.from(buf instanceof ArrayBuffer ? new Uint8Array(buf) : buf).toString("base64");
const attempt = (fn) => {
  try {
    return { ok: fn() };
  } catch (e) {
    return { error: `${e.constructor.name}: ${e.message}` };
  }
};

const ops = {
  quads: ({ blobs }) => blobs.map((blob) => attempt(() => decodeQuadBlob(bytes(blob)).layers.map((l) => ({
    kind: l.kind, width: l.width, height: l.height, rect: l.rect, camera: Array.from(l.camera), count: l.count,
    rows: Array.from(l.rows), cam: attempt(() => layerCamera(l.camera)),
  })))),
  cache: ({ width, height, steps }) => {
    const cache = new QuadCache(width, height);
    return steps.map(({ kind, blob }) => {
      const layer = decodeQuadBlob(bytes(blob)).layers[0];
      const freed = kind === "reset" ? cache.reset(layer.rows, layer.count) : cache.update(layer.rows, layer.count);
      return { freed: freed ?? 0, rows: Array.from(cache.rows), indexMap: b64(new Uint8Array(cache.indexMap.buffer)) };
    });
  },
  session: ({ events }) => {
    const s = new ClientSession(1.5);
    const out = events.map(([name, now, ...args]) => {
      if (name === "connected") return s.connected(now) ?? null;
      if (name === "received") return s.frameReceived(now, ...args);
      if (name === "processed") return s.frameProcessed(now, ...args);
      if (name === "dropped") return s.framesDropped(now, ...args) ?? null;
      if (name === "arrived") return s.frameArrived(now, ...args);
      if (name === "announce") return s.announceReports();
      return s.tick(now);
    });
    return { out, counters: s.counters };
  },
  video: ({ units }) => units.map((u) => ({ idr: isIdr(bytes(u)), codec: codecString(bytes(u)) })),
  encode: ({ hello, poses, reasons, reports = [] }) => ({
    hello: b64(wire.encodeHello(hello)),
    poses: poses.map(([seq, t, p, q, gaze = null]) => attempt(() => b64(wire.encodePoseUpdate(seq, t, p, q, gaze)))),
    reasons: reasons.map((r) => b64(wire.encodeReferenceRequest(r))),
    bye: b64(wire.encodeBye()),
    reports: reports.map((entries) => attempt(() => b64(wire.encodeReceiveReport(entries)))),
  }),
  peek: ({ payloads }) => payloads.map((p) => attempt(() => wire.peekFrameId(bytes(p)))),
  decode: ({ messages }) => messages.map((m) => attempt(() => {
    const raw = bytes(m);
    const msg = wire.decodeMessage(raw.buffer.slice(raw.byteOffset, raw.byteOffset + raw.byteLength));
    if (msg.type !== wire.MessageType.FRAME) return msg;
    const f = wire.decodeFramePayload(msg.payload);
    return { ...f, video: b64(f.video), geometry: b64(f.geometry), type: msg.type };
  })),
  trace: ({ text, times, builtin }) => {
    const parsed = attempt(() => parseQuasarTrace(text, "upload.txt"));
    const poses = times.map((t) => tracePoseAt(builtin, t));
    return { parsed, poses };
  },
  matrices: ({ position, quat, fovy, aspect, yaw, pitch, pointers = [] }) => ({
    gazes: pointers.map(([dx, dy, h]) => gazeAt(dx, dy, h, fovy)),
    view: Array.from(viewMatrix(position, quat)),
    proj: Array.from(projection(symmetricFrustum(fovy, aspect))),
    yawPitch: quatFromYawPitch(yaw, pitch),
  }),
};

process.stdout.write(JSON.stringify(ops[req.op](req)));
