"""The server benchmark (`quadcast bench server`): QUASAR's server along a trace per scene and size, printing
the mean ms per stage, Mbps at 30 fps and the residual/reference byte ratio (QUASAR §4: residual frames are 2-3x
smaller than references). A benchmark, not a test: figures depend on the machine (llvmpipe here)."""
from __future__ import annotations

import tempfile
from pathlib import Path

from quadcast.render.scene import SceneError, load_scene
from quadcast.render.traces import resolve_trace, scene_tour

STAGES = ("gbuffers", "quads", "merge", "gather", "zstd", "video")


def trace_for(scene_spec: str, scene=None):
    """The benchmark trace of a scene: builtin:walk in the courtyard; in the monastery a 5 m circle at 2 m eye
    height in its main courtyard (open space: 5% of every view is farther than 3.5 m, so the camera never walks
    through a wall); a circular tour inside the bounds of any other scene. `scene`: the loaded scene, if at hand."""
    if scene_spec.startswith("builtin:courtyard"):
        return resolve_trace("builtin:walk")
    scene = scene if scene is not None else load_scene(scene_spec)
    if scene_spec == "monastery":
        return scene_tour(scene.bounds(), centre=(-3.7, 1.5), radius=5.0, eye_height=2.0, name="tour:monastery")
    return scene_tour(scene.bounds(), name=f"tour:{scene.name}")


def bench_server(scenes: list[str], sizes: list[tuple[int, int]], frames: int = 20, every: int = 5,
                 viewcell: float = 0.5, crf: float = 23.0, quiet: bool = False) -> list[dict]:
    from quadcast.cli import encode_trace

    rows = []
    print(f"{'scene':20s} {'size':>9s} " + " ".join(f"{s:>8s}" for s in STAGES)
          + f" {'Mbps@30':>8s} {'res/ref':>7s} {'quads':>7s}", flush=True)
    for spec in scenes:
        try:
            trace = trace_for(spec)
        except SceneError as exc:
            print(f"skip {spec}: {exc}")
            continue
        for w, h in sizes:
            with tempfile.TemporaryDirectory() as tmp:
                stats = encode_trace(spec, trace, (w, h), frames, viewcell, every, Path(tmp), crf=crf, quiet=quiet)
            ms = stats["mean_ms"]
            quads = sum(f["quads"] for f in stats["frames"]) / len(stats["frames"])
            ratio = stats["residual_to_reference_bytes"]
            row = {"scene": spec, "size": f"{w}x{h}", "frames": frames, "ms": ms, "mbps_at_30fps":
                   stats["mbps_at_30fps"], "residual_to_reference_bytes": ratio, "mean_quads": quads}
            rows.append(row)
            print(f"{spec:20s} {w:>4d}x{h:<4d} " + " ".join(f"{ms.get(s, float('nan')):8.1f}" for s in STAGES)
                  + f" {row['mbps_at_30fps']:8.2f} {ratio if ratio is not None else float('nan'):7.3f}"
                  f" {quads:7.0f}", flush=True)
    return rows
