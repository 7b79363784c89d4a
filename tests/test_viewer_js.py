"""The viewer page's JavaScript against the Python it reimplements, run under node (tests/viewer_check.mjs):
quad blobs (fzstd from npm, byte planes, normals, float16 offsets), the quad cache, the client session's
decisions, the wire messages and frame header, H.264 codec strings, traces and matrices. No browser needed.
"""
from __future__ import annotations

import base64
import json
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from quadcast.codec.encoder import AtlasEncoder
from quadcast.codec.nal import contains_idr
from quadcast.protocol.errors import ProtocolError
from quadcast.protocol.frame import FramePayload, FrameType, Method, encode_frame_payload, peek_frame_id
from quadcast.protocol.pose import gaze_direction
from quadcast.protocol.messages import (Bye, ErrorMessage, Frame, Hello, PoseUpdate, ReceiveReport, ReferenceRequest,
                                        Welcome, encode_message)
from quadcast.protocol.quads import (MAX_SIZE_LOG2, OFFSETS_PER_QUAD, LayerKind, QuadFrame, QuadLayer, QuadSet,
                                    decode_quad_frame, encode_quad_frame)
from quadcast.protocol.session import ClientSession
from quadcast.render.camera import Camera, Frustum, Pose
from quadcast.render.quadcache import QuadCache
from quadcast.render.quadmesh import quads_to_gpu
from quadcast.render.traces import builtin_trace, parse_trace

ROOT = Path(__file__).resolve().parents[1]
CHECK = ROOT / "tests" / "viewer_check.mjs"
FZSTD = ROOT / "server" / "viewer" / "node_modules" / "fzstd" / "esm" / "index.mjs"


def run_js(tmp_path: Path, request: dict):
    node = shutil.which("node")
    assert node, "node is needed for the viewer's JavaScript tests (the machine's Node.js; make setup uses npm)"
    assert FZSTD.exists(), f"{FZSTD} is missing: run `make setup` (npm ci in server/viewer)"
    path = tmp_path / f"request_{request['op']}.json"
    path.write_text(json.dumps(request))
    r = subprocess.run([node, str(CHECK), str(path)], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    return json.loads(r.stdout)


def b64(data: bytes) -> str:
    return base64.b64encode(bytes(data)).decode()


def quads(rng: np.random.Generator, n: int, width: int, height: int, max_size_log2: int = MAX_SIZE_LOG2) -> QuadSet:
    flat = rng.random(n) < 0.4
    normal = rng.normal(size=(n, 3))
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    return QuadSet(x=rng.integers(0, width, n), y=rng.integers(0, height, n),
                   size_log2=rng.integers(0, max_size_log2 + 1, n), flattened=flat, alpha=rng.random(n) < 0.2,
                   normal=normal, depth=rng.uniform(0.2, 80.0, n),
                   offsets=rng.normal(scale=0.1, size=(int((~flat).sum()), OFFSETS_PER_QUAD)))


def camera(seed: int, width: int, height: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    q = rng.normal(size=4)
    return Camera(Pose(rng.normal(size=3), q), Frustum.symmetric(60.0, width / height, 0.1, 100.0),
                  width, height).to_array()


def test_quad_blobs_decode_to_the_rows_the_python_mesh_uses(tmp_path):
    rng = np.random.default_rng(1)
    frames = [QuadFrame([QuadLayer(LayerKind.VISIBLE, 96, 54, camera(0, 96, 54), (0, 0, 96, 54),
                                   quads(rng, 300, 96, 54)),
                         QuadLayer(LayerKind.HIDDEN, 48, 27, camera(1, 48, 27), (96, 0, 48, 27),
                                   quads(rng, 40, 48, 27)),
                         QuadLayer(LayerKind.WIDE, 64, 36, camera(2, 64, 36), (0, 54, 64, 36), QuadSet.empty())]),
              QuadFrame([])]
    blobs = [encode_quad_frame(f) for f in frames]
    good = blobs[0]
    bad = {"truncated": good[:-5], "bad magic": b"XXXX" + good[4:], "flags set": good[:6] + b"\x01" + good[7:],
           "garbage payload": good[:12 + 3 * 85] + bytes(40)}
    out = run_js(tmp_path, {"op": "quads", "blobs": [b64(b) for b in blobs + list(bad.values())]})
    for blob, got in zip(blobs, out[:2]):
        frame = decode_quad_frame(blob)                   # what the Python client gets (normals quantized)
        assert "ok" in got, got
        assert len(got["ok"]) == len(frame.layers)
        for layer, js in zip(frame.layers, got["ok"]):
            assert (js["kind"], js["width"], js["height"], tuple(js["rect"])) == (
                layer.kind, layer.width, layer.height, layer.atlas_rect)
            np.testing.assert_array_equal(np.float32(js["camera"]), layer.camera)
            rows = np.asarray(js["rows"], np.float32).reshape(-1, 24)
            expected, _ = quads_to_gpu(layer.quads)
            head = expected[:, :4].view(np.uint32)[:, :3].astype(np.float32)
            np.testing.assert_array_equal(rows[:, :3], head)                    # x, y, size_log2
            np.testing.assert_allclose(rows[:, 4:], expected[:, 4:], rtol=0, atol=2e-7)   # normal, depth, offsets
            cam = js["cam"]["ok"]
            np.testing.assert_allclose(cam["position"], layer.camera[:3], rtol=1e-6)
            np.testing.assert_allclose(np.abs(np.dot(cam["quat"], layer.camera[3:7] / np.linalg.norm(
                layer.camera[3:7]))), 1.0, atol=1e-6)
    for (name, blob), got in zip(bad.items(), out[2:]):
        with pytest.raises(ProtocolError):
            decode_quad_frame(blob)
        assert "QuadBlobError" in got.get("error", ""), f"{name}: the page accepted what Python refuses: {got}"


def test_quad_cache_updates_like_the_python_cache(tmp_path):
    rng = np.random.default_rng(2)
    w, h = 40, 30
    steps = [("reset", quads(rng, 120, w, h, 3))] + [("update", quads(rng, n, w, h, 2)) for n in (30, 0, 60, 5)]
    py = QuadCache(w, h)
    blobs, expected = [], []
    for kind, qs in steps:
        qs = decode_quad_frame(encode_quad_frame(QuadFrame([QuadLayer(LayerKind.UPDATED, w, h, camera(0, w, h),
                                                                      (0, 0, w, h), qs)]))).layers[0].quads
        freed = py.reset(qs) if kind == "reset" else py.update(qs)
        expected.append((freed or 0, quads_to_gpu(py.quads)[0], py.index_map.copy()))
        layer = QuadLayer(LayerKind.UPDATED, w, h, camera(0, w, h), (0, 0, w, h), qs)
        blobs.append({"kind": kind, "blob": b64(encode_quad_frame(QuadFrame([layer])))})
    out = run_js(tmp_path, {"op": "cache", "width": w, "height": h, "steps": blobs})
    assert any(f for f, _, _ in expected), "the sequence should free some quads"
    for (freed, rows, index_map), got in zip(expected, out):
        js_map = np.frombuffer(base64.b64decode(got["indexMap"]), np.int32).reshape(h, w)
        np.testing.assert_array_equal(js_map, index_map)
        assert got["freed"] == freed
        js_rows = np.asarray(got["rows"], np.float32).reshape(-1, 24)
        np.testing.assert_array_equal(js_rows[:, :3], rows[:, :4].view(np.uint32)[:, :3].astype(np.float32))
        np.testing.assert_allclose(js_rows[:, 7:], rows[:, 7:], atol=2e-7)


def test_client_session_decides_like_the_python_core(tmp_path):
    rng = np.random.default_rng(3)
    events, now, frame_id = [["connected", 0.0]], 0.0, 0
    for _ in range(300):
        now += float(rng.uniform(0.0, 0.4))
        r = rng.random()
        if r < 0.5:
            frame_id += int(rng.choice([1, 1, 1, 2, 4]))
            events.append(["received", now, frame_id, bool(rng.random() < 0.2)])
        elif r < 0.8:
            events.append(["processed", now, bool(rng.random() < 0.7), bool(rng.random() < 0.3), "reason"])
        elif r < 0.85:
            events.append(["dropped", now, int(rng.integers(1, 4)), "overflow"])
        elif r < 0.88:
            events.append(["connected", now])
        elif r < 0.94:
            events.append(["arrived", now, frame_id + 1, int(rng.integers(100, 200_000))])
        elif r < 0.95:
            events.append(["announce", now])
        else:
            events.append(["tick", now])
    py = ClientSession(1.5)
    calls = {"connected": py.connected, "received": py.frame_received, "processed": py.frame_processed,
             "dropped": py.frames_dropped, "tick": py.tick, "arrived": py.frame_arrived,
             "announce": lambda t: py.announce_reports()}
    expected = []
    for name, t, *args in events:
        result = calls[name](t, *args)
        if hasattr(result, "entries"):          # a SendReport: the page's report is its entries
            result = [list(e) for e in result.entries]
        expected.append(result.reason if hasattr(result, "reason") else result)
    out = run_js(tmp_path, {"op": "session", "events": events})
    assert out["out"] == expected
    c = py.counters
    assert [out["counters"][k] for k in ("framesArrived", "framesReceived", "framesApplied", "framesRejected",
                                         "framesSkipped", "framesLost", "referenceRequests")] == [
        c.frames_arrived, c.frames_received, c.frames_applied, c.frames_rejected, c.frames_skipped, c.frames_lost,
        c.reference_requests]
    assert c.frames_arrived > 0 and any(e[0] == "announce" for e in events)
    assert c.reference_requests > 0 and c.frames_skipped > 0


def test_wire_messages_match_the_python_protocol(tmp_path):
    out = run_js(tmp_path, {"op": "encode",
                            "hello": {"method": "quasar", "width": 960, "height": 540, "fovyDeg": 60.0,
                                      "token": "s3cr\u00e9t"},
                            "poses": [[7, 1.25, [1.0, 1.6, -2.5], [0.0, 0.3826834, 0.0, 0.9238795]],
                                      [8, 1.5, [1.0, 1.6, -2.5], [0.0, 0.0, 0.0, 1.0], [12.5, -3.25]],
                                      [9, 1.5, [0, 0, 0], [0, 0, 0, 1], [89.0, 0.0]],
                                      [9, 1.5, [0, 0, 0], [0, 0, 0, 1], ["x", 0.0]]],
                            "reasons": ["gap", ""],
                            "reports": [[], [[41, 120_345, 3.25], [42, 9_000, 3.2917]],
                                        [[1, -5, 0.0]], [[1, 5, None]], [[0, 0, 0.0]] * 257]})
    assert base64.b64decode(out["hello"]) == encode_message(Hello(1, "quasar", 960, 540, 60.0, "s3cr\u00e9t"))
    assert base64.b64decode(out["poses"][0]["ok"]) == encode_message(
        PoseUpdate(7, 1.25, [1.0, 1.6, -2.5], [0.0, 0.3826834, 0.0, 0.9238795]))
    assert base64.b64decode(out["poses"][1]["ok"]) == encode_message(                 # with the viewer's gaze
        PoseUpdate(8, 1.5, [1.0, 1.6, -2.5], [0.0, 0.0, 0.0, 1.0], (12.5, -3.25)))
    assert [p["error"].split(":")[1].strip() for p in out["poses"][2:]] == ["PoseUpdate.gaze"] * 2
    assert [base64.b64decode(r) for r in out["reasons"]] == [encode_message(ReferenceRequest("gap")),
                                                            encode_message(ReferenceRequest(""))]
    assert base64.b64decode(out["bye"]) == encode_message(Bye())
    assert [base64.b64decode(r["ok"]) for r in out["reports"][:2]] == [
        encode_message(ReceiveReport(())), encode_message(ReceiveReport(((41, 120_345, 3.25), (42, 9_000, 3.2917))))]
    assert [r["error"].split(":")[1].strip() for r in out["reports"][2:]] == [
        "ReceiveReport.entries[0].bytes", "ReceiveReport.entries[0].t_arrive", "ReceiveReport.count"]

    payload = FramePayload(Method.QUASAR, 41, FrameType.RESIDUAL, 40, 3.5, np.array([1.0, 2.0, 3.0]),
                           np.array([0.0, 0.0, 0.0, 1.0]), b"\x00\x00\x00\x01\x41video", b"QDCQgeometry",
                           self_contained=False)
    reference = FramePayload(Method.QUADSTREAM, 5, FrameType.REFERENCE, 5, 0.0, np.zeros(3),
                             np.array([0.0, 1.0, 0.0, 0.0]), b"v", b"", self_contained=True)
    messages = [encode_message(Welcome(12, 30.0)), encode_message(ErrorMessage(5, "Hello.token: wrong")),
                encode_message(Frame(encode_frame_payload(payload))), encode_message(Frame(encode_frame_payload(reference))),
                encode_message(Bye()),
                encode_message(Welcome(1, 30.0))[:-1],                         # truncated
                encode_message(Frame(encode_frame_payload(payload)[:-1])),    # lengths disagree
                encode_message(PoseUpdate(1, 0.0, [0, 0, 0], [0, 0, 0, 1]))]  # not server -> client
    got = run_js(tmp_path, {"op": "decode", "messages": [b64(m) for m in messages]})
    assert got[0]["ok"] == {"type": 2, "sessionId": 12, "serverHz": 30.0}
    assert got[1]["ok"] == {"type": 6, "code": 5, "text": "Hello.token: wrong"}
    f = got[2]["ok"]
    assert (f["method"], f["frameType"], f["selfContained"], f["frameId"], f["referenceId"], f["t"]) == (
        0, 1, False, 41, 40, 3.5)
    assert f["position"] == [1.0, 2.0, 3.0] and f["quat"] == [0.0, 0.0, 0.0, 1.0]
    assert base64.b64decode(f["video"]) == payload.video and base64.b64decode(f["geometry"]) == payload.geometry
    r = got[3]["ok"]
    assert (r["method"], r["frameType"], r["selfContained"], r["frameId"]) == (1, 0, True, 5)
    assert got[4]["ok"] == {"type": 7}
    assert all("WireError" in g.get("error", "") for g in got[5:]), got[5:]
    peeked = run_js(tmp_path, {"op": "peek", "payloads": [b64(encode_frame_payload(payload)), b64(b"QDCF\x02\x00")]})
    assert peeked[0]["ok"] == peek_frame_id(encode_frame_payload(payload)) == 41
    assert "too short for a frame id" in peeked[1]["error"]


def test_codec_string_and_idr_detection_from_our_encoder(tmp_path):
    units = []
    for w, h in ((320, 180), (960, 540)):
        enc = AtlasEncoder(w, h)
        img = np.random.default_rng(0).integers(0, 255, (h, w, 3), np.uint8)
        units += [enc.encode(img, keyframe=True).data, enc.encode(img, keyframe=False).data]
    out = run_js(tmp_path, {"op": "video", "units": [b64(u) for u in units]})
    assert [o["idr"] for o in out] == [contains_idr(u) for u in units] == [True, False, True, False]
    # x264's ultrafast preset: Constrained Baseline (profile_idc 66, constraint flags 0xC0), the level by size
    for unit, o in zip(units[::2], out[::2]):
        sps = unit[unit.index(b"\x00\x00\x01\x67") + 4:]
        assert o["codec"] == f"avc1.42C0{sps[2]:02X}" and sps[:2] == b"\x42\xc0"
    assert out[0]["codec"] == "avc1.42C015"      # level 2.1 at 320x180
    assert out[1]["codec"] is None


def test_traces_and_matrices_follow_the_python_conventions(tmp_path):
    walk = builtin_trace("walk")
    text = walk.slice(0.0, 2.0).to_text()
    times = [float(t) for t in np.linspace(walk.times[0] - 1, walk.times[-1] + 1, 37)]
    small = {"times": walk.times.tolist(), "positions": walk.positions.tolist(), "quats": walk.quats.tolist()}
    out = run_js(tmp_path, {"op": "trace", "text": text, "times": times, "builtin": small})
    parsed, py = out["parsed"]["ok"], parse_trace(text)
    np.testing.assert_allclose(parsed["times"], py.times, atol=1e-9)
    np.testing.assert_allclose(np.abs(np.sum(np.asarray(parsed["quats"]) * py.quats, axis=1)), 1.0, atol=1e-6)
    for t, pose in zip(times, out["poses"]):
        p, q = walk.pose_at(t)
        np.testing.assert_allclose(pose["position"], p, atol=1e-9)
        assert abs(np.dot(pose["quat"], q)) == pytest.approx(1.0, abs=1e-9)
    bad = run_js(tmp_path, {"op": "trace", "text": "0 1.6 0 0 0 0 10\n0 1.6 0 0 nan 0 20\n", "times": [],
                            "builtin": small})
    assert "upload.txt:2: yaw" in bad["parsed"]["error"]

    pose = Pose([1.0, 1.6, -2.0], [0.1, 0.7, -0.2, 0.6])
    m = run_js(tmp_path, {"op": "matrices", "position": pose.position.tolist(), "quat": pose.quat.tolist(),
                          "fovy": 75.0, "aspect": 16 / 9, "yaw": 30.0, "pitch": -10.0,
                          "pointers": [[80.0, 45.0, 180.0], [-120.0, -10.0, 180.0], [0.0, 0.0, 360.0]]})
    np.testing.assert_allclose(np.reshape(m["view"], (4, 4)).T, pose.view_matrix(), atol=1e-12)
    np.testing.assert_allclose(np.reshape(m["proj"], (4, 4)).T, Frustum.symmetric(75.0, 16 / 9).projection_matrix(),
                               atol=1e-12)
    assert abs(np.dot(m["yawPitch"], Pose.from_euler([0, 0, 0], -10.0, 30.0).quat)) == pytest.approx(1.0)
    # the page's pointer gaze: the direction (gaze_direction) of the pixel dx right of and dy above the view's centre
    for (dx, dy, h), g in zip([[80.0, 45.0, 180.0], [-120.0, -10.0, 180.0], [0.0, 0.0, 360.0]], m["gazes"]):
        f = h / 2 / np.tan(np.radians(75.0) / 2)
        ray = np.array([dx / f, dy / f, -1.0])
        np.testing.assert_allclose(gaze_direction(g), ray / np.linalg.norm(ray), atol=1e-12)
