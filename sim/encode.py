"""QUASAR's server along a trace with no network (`quadcast encode`, `quadcast bench server`): every frame's payload,
the H.264 stream and per-frame figures."""
from __future__ import annotations

import json
import sys
from dataclasses import asdict
from pathlib import Path

import numpy as np
from tqdm import tqdm

from quadcast.codec.encoder import VideoSettings
from quadcast.protocol.frame import encode_frame_payload, residual_to_reference_bytes
from quadcast.protocol.methods import method_video
from quadcast.render.camera import Pose
from quadcast.render.renderer import DeferredRenderer
from quadcast.render.scene import load_scene
from quadcast.render.traces import Trace, resolve_trace
from quadcast.server.quasar import QuasarServer, QuasarSettings

__all__ = ["encode_trace"]


def encode_trace(scene_spec: str, trace_spec: str, size: tuple[int, int], frames: int, viewcell: float,
                 every: int, out: Path, layers: int = 4, crf: float | None = None, server_hz: float = 30.0,
                 quiet: bool = False) -> dict:
    """Run QUASAR's server along a trace (poses at `server_hz`, no network); write every frame's payload, the
    H.264 stream and stats.json. Returns the stats."""
    scene = load_scene(scene_spec)
    trace = trace_spec if isinstance(trace_spec, Trace) else resolve_trace(trace_spec)
    if frames < 1:
        raise ValueError(f"--frames must be >= 1, got {frames}")
    times = np.arange(frames) / server_hz
    if times[-1] > trace.duration:
        raise ValueError(f"trace {trace.name!r} lasts {trace.duration:.3f} s; {frames} frames at {server_hz:g} Hz "
                         f"need {times[-1]:.3f} s")
    settings = QuasarSettings(width=size[0], height=size[1], layers=layers, viewcell_radius=viewcell,
                              reference_every=every, video=VideoSettings(**method_video("quasar", crf)))
    server = QuasarServer(DeferredRenderer(scene), settings)
    out.mkdir(parents=True, exist_ok=True)
    records, kinds = [], []
    with open(out / "atlas.h264", "wb") as stream:
        for i, t in enumerate(tqdm(times, desc="encode", unit="frame", disable=quiet, leave=False, file=sys.stderr)):
            p, q = trace.pose_at(trace.times[0] + t)
            payload = server.encode(Pose(p, q), float(t))
            (out / f"frame_{i:05d}.bin").write_bytes(encode_frame_payload(payload))
            stream.write(payload.video)
            kinds.append((payload.frame_type, len(payload.video) + len(payload.geometry)))
            records.append({"frame_id": payload.frame_id, "type": payload.frame_type.name.lower(),
                            "self_contained": payload.self_contained, "bytes_video": len(payload.video),
                            "bytes_geometry": len(payload.geometry), **asdict(payload.stats)})
    server.close()
    total = sum(n for _, n in kinds)
    stats = {
        "scene": scene_spec, "trace": trace.name, "size": f"{size[0]}x{size[1]}", "viewcell_m": viewcell,
        "layers": layers, "reference_every": every, "server_hz": server_hz, "frames": records,
        "residual_to_reference_bytes": residual_to_reference_bytes(kinds),
        "mbps_at_30fps": total * 8 / len(records) * 30 / 1e6,
        "mean_ms": {k: float(np.mean([r["ms"][k] for r in records])) for k in records[0]["ms"]},
    }
    (out / "stats.json").write_text(json.dumps(stats, indent=1))
    return stats
