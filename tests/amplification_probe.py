"""Issue 13, item 7 (run as a script by tests/test_reliability.py; not a test module): feed small blobs that
declare huge outputs to the method clients of a 320x180 session and report, as JSON, what each raised and how
much the process's peak RSS grew.

``gen DIR`` writes the H.264 pieces (made here, so the encoder's memory is not in the measuring process);
``measure DIR`` builds the clients, warms their decoders up on well-formed input, then measures.
"""
import json
import resource
import struct
import sys
from pathlib import Path

import numpy as np
import zstandard

W, H = 320, 180


def depth_bomb() -> bytes:
    """The issue's: a depth blob declaring a 16,777,216 x 1 map (all sky), padded to 8 rows."""
    width, height = 1 << 24, 1
    blocks = width // 8               # mins | maxs (zeros), then the 8-row padded indices (sky), one zstd frame
    cobj = zstandard.ZstdCompressor(level=19, write_content_size=True).compressobj(size=8 * blocks + 8 * width)
    zeros, sky = bytes(1 << 20), b"\xff" * (1 << 20)
    parts = [cobj.compress(zeros) for _ in range(8 * blocks >> 20)]
    parts += [cobj.compress(sky) for _ in range(8 * width >> 20)]
    parts.append(cobj.flush())
    return struct.pack("<4sBBHII", b"QDDP", 1, 8, 0, width, height) + b"".join(parts)


def quad_bomb() -> bytes:
    """8 Mi flattened quads in one 4096 x 2048 visible layer (zeros but the flattened bit)."""
    from quadcast.protocol.quads import HEADER_STRUCT, LAYER_STRUCT
    n = 1 << 23
    cobj = zstandard.ZstdCompressor(level=19, write_content_size=True).compressobj(size=10 * n)
    mib = 1 << 20
    parts = [cobj.compress(bytes(mib)) for _ in range(3 * n // mib)]          # word bytes 0-2
    parts += [cobj.compress(b"\x80" * mib) for _ in range(n // mib)]          # word byte 3: flattened
    parts += [cobj.compress(bytes(mib)) for _ in range(6 * n // mib)]          # theta, phi, depth planes
    parts.append(cobj.flush())
    head = HEADER_STRUCT.pack(b"QDCQ", 3, 0, 1, 10 * n)
    layer = LAYER_STRUCT.pack(0, 4096, 2048, 0, 0, W, H, *([0.0] * 16), n, 0)
    return head + layer + b"".join(parts)


def gen(folder: Path) -> None:
    from quadcast.codec.encoder import AtlasEncoder, VideoSettings
    for name, (w, h) in {"small": (W, H), "atlas": (2 * W, 3 * H // 2 + 2), "huge": (4096, 4096)}.items():
        enc = AtlasEncoder(w, h, VideoSettings(preset="ultrafast"))
        (folder / f"{name}.h264").write_bytes(enc.encode(np.zeros((h, w, 3), np.uint8), keyframe=True).data)
        enc.close()


def measure(folder: Path) -> dict:
    from quadcast.codec.decoder import VideoError
    from quadcast.methods import make_client
    from quadcast.protocol.depth import decode_depth, encode_depth
    from quadcast.protocol.errors import ProtocolError
    from quadcast.protocol.frame import FramePayload, FrameType, Method
    from quadcast.protocol.methods import MethodConfig
    from quadcast.protocol.quads import LayerKind, QuadFrame, QuadLayer, QuadSet, decode_quad_frame, encode_quad_frame
    from quadcast.render.gl import gl_context
    ctx = gl_context()
    cfg = MethodConfig(width=W, height=H)
    clients = {name: make_client(name, cfg, ctx) for name in ("quasar", "meshwarp", "atw")}
    small, atlas, huge = ((folder / f"{n}.h264").read_bytes() for n in ("small", "atlas", "huge"))
    ok_quads = encode_quad_frame(QuadFrame([QuadLayer(LayerKind.VISIBLE, W, H, np.zeros(16), (0, 0, W, H),
                                                      QuadSet.empty())]))
    ok_depth = encode_depth(np.full((H, W), 3.0))

    def payload(method, video, geometry):
        return FramePayload(method, 0, FrameType.REFERENCE, 0, 0.0, np.zeros(3), np.array([0, 0, 0, 1.0]), video,
                            geometry, True)

    # warm-up on well-formed input: libraries loaded, decoders opened
    decode_quad_frame(ok_quads, size=(W, H))
    decode_depth(ok_depth, size=(W, H))
    clients["meshwarp"].receive(payload(Method.MESHWARP, small, ok_depth))
    clients["atw"].receive(payload(Method.ATW, small, b""))
    bombs = {"depth": depth_bomb(), "quads": quad_bomb()}
    cases = {
        "depth blob 16777216x1 (meshwarp)": lambda: clients["meshwarp"].receive(
            payload(Method.MESHWARP, small, bombs["depth"])),
        "quad blob 8 Mi quads (quasar)": lambda: clients["quasar"].receive(
            payload(Method.QUASAR, atlas, bombs["quads"])),
        "H.264 4096x4096 (atw)": lambda: clients["atw"].receive(payload(Method.ATW, huge, b"")),
        "H.264 4096x4096 (quasar)": lambda: clients["quasar"].receive(payload(Method.QUASAR, huge, ok_quads)),
    }
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    out = {"blob_bytes": {k: len(v) for k, v in bombs.items()}, "video_bytes": len(huge), "errors": {}}
    for name, case in cases.items():
        try:
            case()
            out["errors"][name] = None
        except (ProtocolError, VideoError) as exc:
            out["errors"][name] = f"{type(exc).__name__}: {exc}"
    out["peak_rss_growth_mib"] = (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before) / 1024
    return out


if __name__ == "__main__":
    folder = Path(sys.argv[2])
    if sys.argv[1] == "gen":
        gen(folder)
    else:
        print(json.dumps(measure(folder)))
