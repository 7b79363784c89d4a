"""The benchmarks (`quadcast bench render|server|client|stereo`, `make bench`): speed and size figures, not tests.

Every benchmark runs along each scene's benchmark trace (:func:`trace_for`) and prints one line per scene and size;
figures depend on the machine (Mesa llvmpipe on 2 CPU cores here, not a GPU).

- `bench_render`: ms per frame of the deferred renderer, per pass (shadow map, G-buffer, lighting, read-back).
- `bench_server`: QUASAR's server along the trace: mean ms per stage, Mbps at 30 fps and the residual/reference
  byte ratio (QUASAR §4: residual frames are 2-3x smaller than references).
- `bench_client`: a QUASAR server's frames (reference every 5, residuals between) into a `QuasarClient`: the
  client's stage times -- zstd (quad blob decode), video (H.264 atlas decode), quad_update (quad cache), mesh
  (the atlas planes' upload + compute-shader mesh build), render (forward pass, converting the atlas's colour
  per fragment, + read-back) -- and its cache size.
- `bench_stereo`: every displayed frame made a stereo pair from one mesh render (client.stereo.MeshStereo): the
  left eye drawn from the quad mesh, the right eye synthesized by YORO (mode "yoro") or by YORO plus re-rendering
  the disoccluded pixels from the mesh (mode "rerender"). Quality is the synthesized right eye against the
  ground-truth right eye (the deferred renderer at that eye's pose, IPD 63 mm) and against the right eye rendered
  from the same mesh (which isolates the synthesis error from the streaming error). Cost ratio, as YORO reports
  it: (left render + synthesis [+ mode 2 re-render]) / (left render + right render), both renders of the same
  mesh; stage times are GPU-finished wall clock, medians over the frames, read-backs excluded. A last row runs
  YORO on the deferred renderer's own G-buffer (client.stereo.benchmark_stereo), where the second-eye render it
  saves is a full deferred render.
- `bench_quality` (`quadcast bench quality`): image quality under real head motion, not speed -- each real head
  trace (QUASAR format; default: every .txt in :data:`SHARED_TRACES`) re-anchored at each scene's spawn point, its
  4 s of fastest motion, replayed in virtual time (`quadcast.sim.evaluate.run_eval`) for every method at each link
  latency: FLIP, SSIM, PSNR, holes, Mbps, residual/reference bytes, and quasar's FLIP over MeshWarp's. Its figures
  do not depend on the machine's speed.
"""
from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from quadcast.render.camera import Camera, Pose
from quadcast.render.scene import Scene, SceneError, load_scene
from quadcast.render.traces import Trace, resolve_trace, scene_tour

SERVER_STAGES = ("gbuffers", "cache", "quads", "merge", "gather", "zstd", "video")
SHARED_TRACES = Path(__file__).resolve().parents[2] / "shared" / "traces"
"""Where `quadcast bench quality` looks for real head traces by default: the checkout's ../shared/traces."""
QUALITY_SCENES = ("builtin:courtyard", "monastery")
QUALITY_METHODS = ("quasar", "quadstream", "meshwarp", "meshwarp120", "atw")
QUALITY_LATENCIES = ((20.0, 10.0), (50.0, 20.0))
QUALITY_SECONDS = 4.0
CLIENT_STAGES = ("zstd", "video", "quad_update", "mesh", "render")


def trace_for(scene_spec: str, scene: Scene) -> Trace:
    """The benchmark trace of a scene: builtin:walk in the courtyard; in the monastery a 5 m circle at 2 m eye
    height in its main courtyard (open space: 5% of every view is farther than 3.5 m, so the camera never walks
    through a wall); a circular tour inside the bounds of any other scene."""
    if scene_spec.startswith("builtin:courtyard"):
        return resolve_trace("builtin:walk")
    if scene_spec == "monastery":
        x, _, z = scene.spawn.position
        return scene_tour(scene.bounds(), centre=(x, z), radius=5.0, eye_height=2.0, name="tour:monastery")
    return scene_tour(scene.bounds(), name=f"tour:{scene.name}")


def bench_scenes(specs: list[str]) -> list[tuple[str, Scene, Trace]]:
    """Each scene that loads, with its benchmark trace; a scene that does not load is skipped with a line saying
    why (e.g. the monastery without the `scenes` extra)."""
    out = []
    for spec in specs:
        try:
            scene = load_scene(spec)
        except SceneError as exc:
            print(f"skip {spec}: {exc}", flush=True)
            continue
        out.append((spec, scene, trace_for(spec, scene)))
    return out


def trace_poses(trace: Trace, frames: int, fps: float = 30.0) -> list[tuple[float, Pose]]:
    """(t, pose) of `trace` at `fps`, from its start."""
    return [(k / fps, Pose(*trace.pose_at(trace.times[0] + k / fps))) for k in range(frames)]


def _progress(items, desc: str, quiet: bool):
    return tqdm(items, desc=desc, unit="frame", disable=quiet, leave=False, file=sys.stderr)


def bench_render(scenes: list[str], sizes: list[tuple[int, int]], frames: int = 10) -> list[dict]:
    """ms/frame of the deferred renderer (G-buffer + shadows + lighting + colour read-back) along each scene's
    benchmark trace (`trace_for`)."""
    from quadcast.render.renderer import DeferredRenderer

    rows = []
    for spec, scene, trace in bench_scenes(scenes):
        renderer = DeferredRenderer(scene)
        for w, h in sizes:
            poses = [trace.pose_at(t) for t in np.linspace(0, trace.duration, frames + 1)]
            cams = [Camera.perspective(Pose(p, q), w, h) for p, q in poses]
            renderer.render_color(cams[0], 0.0)  # warm-up: shader compilation, allocation
            stages = {"shadow": 0.0, "geometry": 0.0, "lighting": 0.0, "readback": 0.0}
            t0 = time.perf_counter()
            for k, cam in enumerate(cams[1:]):
                # The passes of render_color, each waited for, so their times add up to the frame's.
                t, gb = k / 30, renderer.gbuffer_for(w, h)
                for stage, run in (("shadow", lambda: renderer.render_shadows(t)),
                                   ("geometry", lambda: renderer.geometry_pass(cam, t, gb)),
                                   ("lighting", lambda: renderer.lighting_pass(gb, t)),
                                   ("readback", gb.read_color)):
                    ts = time.perf_counter()
                    run()
                    renderer.finish()
                    stages[stage] += (time.perf_counter() - ts) * 1000 / frames
            ms = (time.perf_counter() - t0) * 1000 / frames
            rows.append({"scene": spec, "triangles": scene.triangle_count, "size": f"{w}x{h}", "ms_per_frame": ms,
                         "ms": stages})
            parts = "  ".join(f"{k} {v:6.1f}" for k, v in stages.items())
            print(f"{spec:22s} {scene.triangle_count:8d} tris  {w}x{h:<5d} {ms:8.1f} ms/frame  ({parts})", flush=True)
    return rows


def _full_render_ms(renderer, pose: Pose, w: int, h: int, t: float) -> float:
    """Wall-clock ms of one full deferred render of `pose` (colour read back): the unit speed is judged in. It
    draws its own shadow map where shadow casters move (a static scene's is drawn once), not the one the server
    has just drawn for the same time."""
    renderer.forget_shadow_map()
    start = time.perf_counter()
    renderer.render_color(Camera.perspective(pose, w, h), t)
    return (time.perf_counter() - start) * 1e3


def bench_server(scenes: list[str], sizes: list[tuple[int, int]], frames: int = 10, every: int = 5,
                 viewcell: float = 0.5, quiet: bool = False) -> list[dict]:
    """QUASAR's server along each scene's benchmark trace: mean ms per stage and per frame over the frames after
    the first (a warm-up), and, interleaved frame by frame on the same renderer, one full render of the same view:
    `ratio_to_render` is the server frame's wall time over that render's; the server codes with quasar's own video
    settings (`quadcast.protocol.methods.method_video`)."""
    from quadcast.protocol.frame import FrameType, residual_to_reference_bytes
    from quadcast.render.renderer import DeferredRenderer
    from quadcast.server.quasar import QuasarServer, QuasarSettings

    if frames < 2:
        raise ValueError(f"bench server: --frames must be >= 2 (the first frame is a warm-up), got {frames}")
    rows = []
    print(f"{'scene':20s} {'size':>9s} " + " ".join(f"{s:>8s}" for s in SERVER_STAGES)
          + f" {'frame':>8s} {'render':>8s} {'ratio':>6s} {'Mbps@30':>8s} {'res/ref':>7s} {'quads':>7s}", flush=True)
    for spec, scene, trace in bench_scenes(scenes):
        renderer = DeferredRenderer(scene)
        for w, h in sizes:
            server = QuasarServer(renderer, QuasarSettings(width=w, height=h, viewcell_radius=viewcell,
                                                           reference_every=every))
            stage_ms, frame_ms, render_ms, kinds, quads = [], [], [], [], []
            for t, pose in _progress(trace_poses(trace, frames), f"server {spec} {w}x{h}", quiet):
                start = time.perf_counter()
                payload = server.encode(pose, t)
                frame_ms.append((time.perf_counter() - start) * 1e3)
                render_ms.append(_full_render_ms(renderer, pose, w, h, t))
                stage_ms.append(payload.stats.ms)
                kinds.append((payload.frame_type, len(payload.video) + len(payload.geometry)))
                quads.append(payload.stats.quads)
            server.close()
            ms = {k: float(np.mean([f.get(k, 0.0) for f in stage_ms[1:]])) for k in SERVER_STAGES}
            frame, render = float(np.mean(frame_ms[1:])), float(np.mean(render_ms[1:]))
            ratio = residual_to_reference_bytes(kinds)
            row = {"scene": spec, "size": f"{w}x{h}", "frames": frames - 1, "ms": ms, "frame_ms": frame,
                   "render_ms": render, "ratio_to_render": frame / render,
                   "mbps_at_30fps": sum(n for _, n in kinds) * 8 / len(kinds) * 30 / 1e6,
                   "residual_to_reference_bytes": ratio, "mean_quads": float(np.mean(quads)),
                   "residual_frames": sum(k == FrameType.RESIDUAL for k, _ in kinds[1:])}
            rows.append(row)
            print(f"{spec:20s} {w:>4d}x{h:<4d} " + " ".join(f"{ms[s]:8.1f}" for s in SERVER_STAGES)
                  + f" {frame:8.1f} {render:8.1f} {frame / render:6.2f} {row['mbps_at_30fps']:8.2f}"
                  f" {ratio if ratio is not None else float('nan'):7.3f} {row['mean_quads']:7.0f}", flush=True)
    return rows


def bench_client(scenes: list[str], sizes: list[tuple[int, int]], frames: int = 10,
                 quiet: bool = False) -> list[dict]:
    """Client stage times (mean ms over the frames after the first: receive a frame and render it once) and cache
    size at each size, per scene; and, interleaved frame by frame on the same GL context, one full render of the
    same view: `ratio_to_render` is the client frame's time over that render's."""
    from quadcast.client.quasar import QuasarClient
    from quadcast.render.renderer import DeferredRenderer
    from quadcast.server.quasar import QuasarServer, QuasarSettings

    if frames < 2:
        raise ValueError(f"bench client: --frames must be >= 2 (the first frame is a warm-up), got {frames}")
    rows = []
    for spec, scene, trace in bench_scenes(scenes):
        renderer = DeferredRenderer(scene)
        for w, h in sizes:
            server = QuasarServer(renderer, QuasarSettings(width=w, height=h))
            client = QuasarClient(w, h, ctx=renderer.ctx)
            per_frame, kinds, render_ms = [], [], []
            for t, pose in _progress(trace_poses(trace, frames), f"client {spec} {w}x{h}", quiet):
                payload = server.encode(pose, t)
                client.receive(payload)
                client.render(pose)
                per_frame.append(dict(client.stats["ms"]))
                kinds.append(payload.frame_type.name.lower())
                render_ms.append(_full_render_ms(renderer, pose, w, h, t))
            server.close()
            ms = {k: float(np.mean([f[k] for f in per_frame[1:]])) for k in CLIENT_STAGES}
            total, render = float(sum(ms.values())), float(np.mean(render_ms[1:]))
            # Stage times under "ms" (as in the server's rows): a flat "render_ms" is the full render, as there.
            row = {"scene": spec, "size": f"{w}x{h}", "frames": frames - 1,
                   "residual_frames": kinds[1:].count("residual"), "ms": ms,
                   "total_ms": total, "render_ms": render, "ratio_to_render": total / render,
                   "cache_quads": int(client.stats["cache_quads"]),
                   "cache_bytes": int(client.stats["cache_bytes"]), "mesh_quads": int(client.stats["mesh_quads"])}
            rows.append(row)
            print(f"{spec:18s} {w}x{h:<5d} " + " ".join(f"{k} {ms[k]:7.1f}" for k in CLIENT_STAGES)
                  + f"  = {total:7.1f} ms/frame, a full render {render:.1f} ms: ratio {total / render:.2f}"
                    f" | cache {row['cache_quads']} quads "
                    f"{row['cache_bytes'] / 2**20:.2f} MiB, mesh {row['mesh_quads']} quads "
                    f"({row['residual_frames']}/{row['frames']} residual frames)", flush=True)
    return rows


def bench_stereo(scenes: list[str], size: tuple[int, int] = (960, 540), frames: int = 6,
                 quiet: bool = False) -> list[dict]:
    """YORO quality and cost ratio per scene and mode (see the module docstring)."""
    from quadcast.client.quasar import QuasarClient
    from quadcast.client.stereo import StereoSynthesizer, benchmark_stereo
    from quadcast.render.renderer import DeferredRenderer
    from quadcast.server.quasar import QuasarServer, QuasarSettings
    from quadcast.sim.metrics import compare

    if frames < 2:
        raise ValueError(f"bench stereo: --frames must be >= 2 (the first frame is a warm-up), got {frames}")
    w, h = size
    rows = []
    for spec, scene, trace in bench_scenes(scenes):
        renderer = DeferredRenderer(scene)
        server = QuasarServer(renderer, QuasarSettings(width=w, height=h))
        client = QuasarClient(w, h, ctx=renderer.ctx)
        acc: dict[str, list[dict]] = {"yoro": [], "rerender": []}
        poses = trace_poses(trace, frames)
        for k, (t, pose) in enumerate(_progress(poses, f"stereo {spec} {w}x{h}", quiet)):
            client.receive(server.encode(pose, t))
            for mode, records in acc.items():
                f = client.stereo_frame(pose, mode, with_rendered=True)
                if k == 0:
                    continue  # warm-up
                truth = renderer.render_color(Camera.perspective(f.other_camera.pose, w, h), t)
                gt, own = compare(truth, f.synthesized), compare(f.rendered_other, f.synthesized)
                records.append({"ssim": gt.ssim, "psnr": gt.psnr, "flip": gt.flip, "ssim_mesh": own.ssim,
                                "psnr_mesh": own.psnr, "flip_mesh": own.flip,
                                "psnr_rendered_eye": compare(truth, f.rendered_other).psnr,
                                "disoccluded": f.disoccluded_fraction, "rerendered": f.rerender_fraction,
                                **{f"{s}_ms": v for s, v in f.ms.items()}})
        server.close()
        for mode, records in acc.items():
            row = {"scene": spec, "size": f"{w}x{h}", "source": "quad mesh", "mode": mode, "frames": len(records)}
            for key in records[0]:
                values = [r[key] for r in records]
                row[key] = float(np.median(values) if key.endswith("_ms") else np.mean(values))
            row["cost_ratio"] = ((row["dominant_ms"] + row["synthesize_ms"] + row["rerender_ms"])
                                 / (row["dominant_ms"] + row["other_ms"]))
            rows.append(row)
            print(f"{spec:18s} {w}x{h} mesh  {mode:8s} vs truth: SSIM {row['ssim']:.4f} PSNR {row['psnr']:5.2f} dB "
                  f"FLIP {row['flip']:.4f} | vs mesh-rendered eye: SSIM {row['ssim_mesh']:.4f} "
                  f"PSNR {row['psnr_mesh']:5.2f} dB (that eye vs truth {row['psnr_rendered_eye']:5.2f} dB) | "
                  f"holes {100 * row['disoccluded']:.2f}% redo {100 * row['rerendered']:.2f}% | "
                  f"left {row['dominant_ms']:.1f} + synth {row['synthesize_ms']:.1f} + redo {row['rerender_ms']:.1f} "
                  f"ms vs right {row['other_ms']:.1f} ms -> cost {100 * row['cost_ratio']:.1f}% of two renders",
                  flush=True)
        # YORO on the deferred renderer's own G-buffer: the render it saves is a full deferred render.
        t, pose = poses[len(poses) // 2]
        synth = StereoSynthesizer(renderer.ctx, w, h)
        b = benchmark_stereo(renderer, Camera.perspective(pose, w, h), t, synth, repeats=3)
        synth.release()
        for mode, img, extra in (("yoro", b.synthesized, 0.0), ("rerender", b.rerendered, b.rerender_ms)):
            s = compare(b.truth, img)
            cost = (b.render_ms + b.synthesize_ms + extra) / (2 * b.render_ms)
            rows.append({"scene": spec, "size": f"{w}x{h}", "source": "deferred g-buffer", "mode": mode, "frames": 1,
                         "ssim": s.ssim, "psnr": s.psnr, "flip": s.flip, "synthesize_ms": b.synthesize_ms,
                         "rerender_ms": extra, "other_ms": b.render_ms, "cost_ratio": cost})
            print(f"{spec:18s} {w}x{h} gbuf  {mode:8s} vs truth: SSIM {s.ssim:.4f} PSNR {s.psnr:5.2f} dB "
                  f"FLIP {s.flip:.4f} | synth {b.synthesize_ms:.1f} + redo {extra:.1f} ms vs a deferred render "
                  f"{b.render_ms:.1f} ms -> cost {100 * cost:.1f}% of two renders", flush=True)
    return rows


def quality_traces(paths: list[str] | None) -> list[Path]:
    """The trace files of `bench_quality`: `paths`, or every .txt in :data:`SHARED_TRACES` (none when absent)."""
    if paths:
        missing = [p for p in paths if not Path(p).is_file()]
        if missing:
            raise ValueError(f"bench quality: no such trace file(s): {', '.join(missing)}")
        return [Path(p) for p in paths]
    return sorted(SHARED_TRACES.glob("*.txt")) if SHARED_TRACES.is_dir() else []


def bench_quality(traces: list[str] | None = None, scenes=QUALITY_SCENES, methods=QUALITY_METHODS,
                  latencies=QUALITY_LATENCIES, size: tuple[int, int] = (640, 360), frames: int | None = None,
                  every: int = 8, viewcell: float = 0.5, seconds: float = QUALITY_SECONDS, seed: int = 0,
                  out: Path | None = None, quiet: bool = False) -> list[dict]:
    """Quality under real head motion (see the module docstring): one row per scene x trace x latency x method.
    `frames` display frames (default: `seconds` at 60 Hz) from the start of each trace's fastest `seconds`
    (`Trace.fastest_window`), every `every`-th scored. With `out`, each run's outputs go to a folder of it.
    quasar's rows carry ``flip_vs_meshwarp`` (its FLIP / MeshWarp's on the same trace, scene and link) when MeshWarp
    was run too."""
    from quadcast.render.traces import load_trace
    from quadcast.sim.evaluate import EvalSpec, run_eval

    files = quality_traces(traces)
    if not files:
        print(f"skip bench quality: no head traces in {SHARED_TRACES} (give trace files as arguments)", flush=True)
        return []
    frames = int(round(seconds * 60)) if frames is None else frames
    starts = {}
    for path in files:
        trace = load_trace(path)
        starts[path] = trace.fastest_window(seconds)
        print(f"{path.stem}: fastest {seconds:g} s from {starts[path]:.2f} s of {trace.duration:.1f} s", flush=True)
    loaded = [spec for spec, _, _ in bench_scenes(list(scenes))]   # skips (and says why) scenes that do not load
    rows = []
    header = (f"{'scene':18s} {'trace':22s} {'link':>6s} {'method':>11s} {'FLIP':>6s} {'SSIM':>6s} {'PSNR':>6s} "
              f"{'holes%':>7s} {'max%':>6s} {'Mbps':>7s} {'res/ref':>7s}")
    print(header, flush=True)
    for scene in loaded:
        for path in files:
            for lat, jit in latencies:
                group = []
                for method in methods:
                    spec = EvalSpec(scene=scene, trace=str(path), anchor="spawn", start=starts[path], method=method,
                                    latency_ms=lat, jitter_ms=jit, viewcell_m=viewcell, width=size[0],
                                    height=size[1], frames=frames, every=every, seed=seed)
                    name = f"{scene.split(':')[-1]}_{path.stem}_{lat:g}ms_{method}"
                    s = run_eval(spec, out / name if out is not None else None, quiet=quiet)
                    row = {"scene": scene, "trace": path.stem, "start_s": starts[path], "latency_ms": lat,
                           "jitter_ms": jit, "method": method, "size": f"{size[0]}x{size[1]}", "frames": s["frames"],
                           "flip": s["flip"], "ssim": s["ssim"], "psnr": s["psnr"], "holes": s["holes"]["mean"],
                           "holes_max": s["holes"]["max"], "black_frames": s["black_frames"], "mbps": s["mbps"],
                           "residual_to_reference_bytes": s.get("residual_to_reference_bytes"),
                           "pose_error_deg": s["pose_error_deg"]["mean"], "pose_error_cm": s["pose_error_cm"]["mean"]}
                    group.append(row)
                    rows.append(row)
                    _print_quality_row(row)
                by = {r["method"]: r for r in group}
                if "quasar" in by and "meshwarp" in by and by["meshwarp"]["flip"]:
                    by["quasar"]["flip_vs_meshwarp"] = by["quasar"]["flip"] / by["meshwarp"]["flip"]
                    print(f"{'':18s} {'':22s} {lat:>3g}±{jit:<2g} quasar FLIP / MeshWarp's = "
                          f"{by['quasar']['flip_vs_meshwarp']:.3f}", flush=True)
    return rows


def _print_quality_row(r: dict) -> None:
    from quadcast.sim.report import format_figure as f
    pct = lambda v: None if v is None else 100 * v  # noqa: E731
    print(f"{r['scene']:18s} {r['trace'][:22]:22s} {r['latency_ms']:>3g}±{r['jitter_ms']:<2g} {r['method']:>11s} "
          f"{f(r['flip'], '6.4f')} {f(r['ssim'], '6.4f')} {f(r['psnr'], '6.2f')} {f(pct(r['holes']), '7.3f')} "
          f"{f(pct(r['holes_max']), '6.2f')} {f(r['mbps'], '7.2f')} {f(r['residual_to_reference_bytes'], '7.3f')}",
          flush=True)


def format_quality_table(rows: list[dict]) -> str:
    """The rows of `bench_quality` as a markdown table."""
    from quadcast.sim.report import format_figure as f
    pct = lambda v: None if v is None else 100 * v  # noqa: E731
    lines = ["| scene | trace | link (ms) | method | FLIP | SSIM | PSNR (dB) | holes % (max) | Mbps | res/ref | "
             "FLIP / MeshWarp |", "|---|---|---|---|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        lines.append(f"| {r['scene']} | {r['trace']} | {r['latency_ms']:g}±{r['jitter_ms']:g} | {r['method']} | "
                     f"{f(r['flip'], '.4f')} | {f(r['ssim'], '.4f')} | {f(r['psnr'], '.2f')} | "
                     f"{f(pct(r['holes']), '.2f')} ({f(pct(r['holes_max']), '.1f')}) | {f(r['mbps'], '.2f')} | "
                     f"{f(r['residual_to_reference_bytes'], '.3f')} | {f(r.get('flip_vs_meshwarp'), '.3f')} |")
    return "\n".join(lines) + "\n"


# ------------------------------------------------------------------------------------------------- ladder

LADDER_TRACES = "../shared/traces/*.txt"
"""The real head traces `bench ladder` measures on by default (QUASAR's format); it skips when there are none."""

LADDER_START = (-1.5, 1.6, 4.0)
"""Where a real trace's window starts in builtin:courtyard: in the open square, 4 m south of the fountain,
moving along +X, with 3 m clear ahead."""


def placed_window(trace: Trace, seconds: float, start=LADDER_START) -> Trace:
    """`seconds` of a real trace from its middle, moved into the courtyard: its first pose at `start` (eye height
    included), turned about the vertical so that it moves along +X; the head's motion relative to the path is kept."""
    from scipy.spatial.transform import Rotation

    from quadcast.render.traces import euler_to_rotation, rotation_to_euler
    if trace.duration < seconds:
        raise ValueError(f"trace {trace.name!r} lasts {trace.duration:.1f} s, less than the {seconds:g} s needed")
    t0 = float(trace.times[0]) + (trace.duration - seconds) / 2
    w = trace.slice(t0, t0 + seconds)
    move = w.positions[-1] - w.positions[0]
    heading = -np.arctan2(-move[2], move[0]) if np.hypot(move[0], move[2]) > 0.05 else 0.0
    turn = Rotation.from_euler("y", heading)           # the horizontal direction of travel onto +X
    positions = turn.apply(w.positions - w.positions[0]) + np.asarray(start)
    euler = rotation_to_euler(turn * euler_to_rotation(w.euler_deg))
    return Trace(f"{trace.name}@courtyard", w.times - w.times[0], positions, euler)


def ladder_grid() -> list:
    """The operating points `bench ladder` measures: uniform points over frame rate, CRF, quad thresholds and
    hidden layers, and foveated points (merge thresholds and atlas resolution growing away from the view centre)."""
    from quadcast.protocol.rate import OperatingPoint
    points = []
    for fps in (30, 20, 15, 10, 6):
        for crf, quad, hidden in ((23, 1, 3), (23, 1, 1), (23, 4, 1), (28, 4, 1), (28, 4, 0), (33, 8, 0)):
            points.append(OperatingPoint(f"f{fps:g}-c{crf}-q{quad}-h{hidden}", crf=crf, quad_scale=quad,
                                         coarse_passes=3 if quad == 1 else 5, hidden_layers=hidden, fps=fps))
    for crf, quad in ((28, 4), (33, 8)):
        points.append(OperatingPoint(f"f12-c{crf}-q{quad}-h0", crf=crf, quad_scale=quad, coarse_passes=5,
                                     hidden_layers=0, fps=12))
    for fps, sigma, hidden in ((30, 5, 3), (30, 5, 1), (30, 10, 1), (20, 5, 1), (20, 10, 1), (15, 5, 1),
                               (15, 10, 1)):
        points.append(OperatingPoint(f"fov{sigma}-f{fps:g}-c23-h{hidden}", hidden_layers=hidden, fps=fps,
                                     fovea_sigma_deg=sigma, fovea_max_scale=32, fovea_atlas=4))
    for fps, sigma in ((30, 10), (20, 10), (15, 10), (15, 5)):
        points.append(OperatingPoint(f"fov{sigma}-f{fps:g}-c28-q4-h0", crf=28, quad_scale=4, coarse_passes=5,
                                     hidden_layers=0, fps=fps, fovea_sigma_deg=sigma, fovea_max_scale=32,
                                     fovea_atlas=4))
    return points


def code_fingerprint(root: Path | None = None) -> str:
    """A hash of the code under `root` (default: the installed quadcast package): every .py and shader file's path
    and bytes, symlinked folders followed. `bench ladder` keys the rows it keeps to it, so that rows measured by
    other code are measured again rather than reused."""
    import hashlib
    import os

    import quadcast
    root = Path(quadcast.__file__).parent if root is None else Path(root)
    digest = hashlib.sha256()
    files = []
    for folder, dirs, names in os.walk(root, followlinks=True):
        dirs[:] = sorted(d for d in dirs if d != "__pycache__")
        files += [Path(folder) / n for n in names if n.endswith((".py", ".glsl", ".comp"))]
    for path in sorted(files):
        digest.update(str(path.relative_to(root)).encode() + b"\0" + path.read_bytes() + b"\0")
    return digest.hexdigest()[:16]


def reusable_ladder_rows(all_json: Path, run: dict) -> dict:
    """The rows of an earlier `bench ladder` (its all.json) that were measured in the same `run` -- size, frames,
    link, traces and code -- by point name; none when the file is missing."""
    import json
    if not all_json.exists():
        return {}
    return {r["name"]: r for r in json.loads(all_json.read_text()) if r.get("run") == run}


def _ladder_point(point, traces: list[str], size: tuple[int, int], frames: int, every: int,
                  latency: tuple[float, float]) -> list[dict]:
    """One point on every trace (run in a process of its own: the GL objects of a run are not all released)."""
    from quadcast.sim.evaluate import EvalSpec, run_eval
    return [run_eval(EvalSpec(scene="builtin:courtyard", trace=t, method="quasar", latency_ms=latency[0],
                              jitter_ms=latency[1], width=size[0], height=size[1], frames=frames, every=every,
                              point=point)) for t in traces]


def bench_ladder(traces: list[str] | None = None, size: tuple[int, int] = (640, 360), frames: int = 48,
                 every: int = 4, latency: tuple[float, float] = (20.0, 10.0), out: Path | None = None,
                 write: str | None = None, points: list | None = None, command: str = "",
                 quiet: bool = False) -> list[dict]:
    """Every point of :func:`ladder_grid` (or `points`) on each real trace (a `frames`/60 s window from its middle,
    placed in builtin:courtyard by :func:`placed_window`), in virtual-time replay with no rate limit: Mbps, FLIP
    and FLIP over the central 20 degrees, averaged over the traces. Prints the table and the Pareto front of (Mbps,
    FLIP); writes `all.json`, `front.json` and `ladder.png` to `out`, and with `write` the ladder
    (:func:`quadcast.protocol.rate.ladder_points`: the Pareto front at each frame-rate floor) as the file the rate
    controller loads (`protocol/ladder.json`), with `command`. Points already in `out`/all.json with the same
    settings and run, measured by the same code (`code_fingerprint`), are taken from there, not measured again.
    Returns one row per point."""
    import glob
    import json
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor
    from dataclasses import replace

    from quadcast.protocol.rate import Ladder, ladder_points, pareto_front
    from quadcast.render.traces import load_trace

    paths = sorted(glob.glob(LADDER_TRACES)) if traces is None else traces
    if not paths:
        print(f"bench ladder: skipped, no traces ({LADDER_TRACES} matches nothing)", flush=True)
        return []
    out = Path(out) if out is not None else Path("out/ladder")
    (out / "traces").mkdir(parents=True, exist_ok=True)
    placed = []
    for p in paths:
        t = placed_window(load_trace(p), frames / 60.0 + 0.1)
        path = out / "traces" / f"{Path(p).stem}.txt"
        t.save(path)
        placed.append(str(path))
    grid = points if points is not None else ladder_grid()
    run = {"size": list(size), "frames": frames, "every": every, "latency": list(latency),
           "traces": [Path(p).stem for p in paths], "code": code_fingerprint()}
    known = reusable_ladder_rows(out / "all.json", run)
    rows, measured = [], []
    pool = ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn"), max_tasks_per_child=1)
    for point in tqdm(grid, desc="ladder", unit="point", disable=quiet, file=sys.stderr):
        old = known.get(point.name)
        if old is not None and all(old.get(k) == v for k, v in point.knobs().items()):
            row = old
        else:
            runs = pool.submit(_ladder_point, point, placed, size, frames, every, latency).result()
            row = {"name": point.name, **point.knobs(), "mbps": float(np.mean([r["mbps"] for r in runs])),
                   "flip": float(np.mean([r["flip"] for r in runs])),
                   "flip_fovea": float(np.mean([r["flip_fovea"] for r in runs])), "run": run,
                   "per_trace": {Path(t).stem: {k: r[k] for k in ("mbps", "flip", "flip_fovea")}
                                 for t, r in zip(placed, runs)}}
        rows.append(row)
        measured.append(replace(point, mbps=row["mbps"], flip=row["flip"], flip_fovea=row["flip_fovea"]))
        print(f"{point.name:24s} {row['mbps']:7.2f} Mbps  FLIP {row['flip']:.4f}  fovea {row['flip_fovea']:.4f}",
              flush=True)
    pool.shutdown()
    front = pareto_front(measured)
    ladder = Ladder(tuple(ladder_points(measured)), size, 30.0, command,
                    f"Pareto fronts of (Mbps, FLIP) at each frame-rate floor over {len(measured)} points on "
                    f"{len(placed)} real traces ({', '.join(Path(p).stem for p in paths)}), {frames} display "
                    f"frames each from the middle, placed in builtin:courtyard, {latency[0]:g}+-{latency[1]:g} ms, "
                    f"virtual-time replay, no rate limit")
    (out / "all.json").write_text(json.dumps(rows, indent=1))
    (out / "front.json").write_text(ladder.to_json())
    if write:
        Path(write).write_text(ladder.to_json())
    plot_ladder(measured, front, list(ladder.points), out / "ladder.png")
    print("\nladder (Pareto fronts at each frame-rate floor; * = on the front of all points):")
    for p in ladder.points:
        print(f"  {p.name:24s} {p.fps:4g} fps {p.mbps:7.2f} Mbps  FLIP {p.flip:.4f}  fovea {p.flip_fovea:.4f}"
              f"{'  *' if p in front else ''}", flush=True)
    return rows


def plot_ladder(points: list, front: list, ladder: list, path: Path) -> Path:
    """Every measured point (uniform and foveated) in (Mbps, FLIP), the Pareto front drawn through, the ladder's
    points ringed."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    fig = Figure(figsize=(7, 4.2), dpi=100, layout="constrained")
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    for foveated, colour, label in ((False, "tab:blue", "uniform"), (True, "tab:orange", "foveated")):
        sel = [p for p in points if p.foveated == foveated]
        if sel:
            ax.scatter([p.mbps for p in sel], [p.flip for p in sel], s=14, color=colour, alpha=0.6, label=label)
    ax.plot([p.mbps for p in front], [p.flip for p in front], color="black", lw=1.2, label="Pareto front")
    ax.scatter([p.mbps for p in ladder], [p.flip for p in ladder], s=60, facecolors="none", edgecolors="black",
               label="the ladder (front at each frame-rate floor)")
    for p in ladder:
        ax.annotate(f"{p.fps:g}", (p.mbps, p.flip), textcoords="offset points", xytext=(4, 3), fontsize=6)
    ax.set_xlabel("Mbit/s")
    ax.set_ylabel("FLIP ↓")
    ax.set_title("Operating points (quadcast bench ladder)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.savefig(path, metadata={"Software": None})
    return path
