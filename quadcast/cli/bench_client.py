"""Client benchmarks (not tests): `quadcast bench client` and `quadcast bench stereo`.

`bench_client` streams a QUASAR server's frames (reference every 5, residuals between) into a `QuasarClient` along
a short walk and prints the client's stage times -- zstd (quad blob decode), video (H.264 atlas decode),
quad_update (quad cache), mesh (upload + compute-shader mesh build), render (forward pass + read-back), ms -- and
its cache size (quads, bytes).

`bench_stereo` does the same at one size and makes every displayed frame a stereo pair from one mesh render
(client.stereo.MeshStereo): the left eye drawn from the quad mesh, the right eye synthesized by YORO (mode
"yoro") or by YORO plus re-rendering the disoccluded pixels from the mesh (mode "rerender"). Quality is the
synthesized right eye against the ground-truth right eye (the deferred renderer at that eye's pose, IPD 63 mm) and
against the right eye rendered from the same mesh (which isolates the synthesis error from the streaming error).
Cost ratio, as YORO reports it: (left render + synthesis [+ mode 2 re-render]) / (left render + right render),
both renders of the same mesh; stage times are GPU-finished wall clock, medians over the frames, read-backs
excluded. A last row runs YORO on the deferred renderer's own G-buffer (client.stereo.benchmark_stereo), where
the second-eye render it saves is a full deferred render.

Times are for this machine's GL (Mesa llvmpipe on 2 CPU cores here), not a GPU.
"""
from __future__ import annotations

import numpy as np

from quadcast.render.camera import Camera, Pose
from quadcast.render.scene import Scene, SceneError, load_scene

CLIENT_STAGES = ("zstd", "video", "quad_update", "mesh", "render")


def walk_poses(spec: str, scene: Scene, frames: int, fps: float = 30.0) -> list[tuple[float, Pose]]:
    """(t, pose) of the scene's benchmark trace (:func:`quadcast.cli.bench.trace_for`) at `fps`, from its start."""
    from quadcast.cli.bench import trace_for
    trace = trace_for(spec, scene)
    return [(k / fps, Pose(*trace.pose_at(trace.times[0] + k / fps))) for k in range(frames)]


def _scenes(specs: list[str]) -> list[tuple[str, Scene]]:
    out = []
    for spec in specs:
        try:
            out.append((spec, load_scene(spec)))
        except SceneError as exc:
            print(f"skip {spec}: {exc}", flush=True)
    return out


def bench_client(scenes: list[str], sizes: list[tuple[int, int]], frames: int = 10, crf: float = 23.0,
                 quiet: bool = False) -> list[dict]:
    """Client stage times (mean ms over the frames after the first) and cache size at each size, per scene."""
    from tqdm import tqdm

    from quadcast.client.quasar import QuasarClient
    from quadcast.render.renderer import DeferredRenderer
    from quadcast.server.quasar import QuasarServer, QuasarSettings
    from quadcast.codec.encoder import VideoSettings

    if frames < 2:
        raise ValueError(f"bench client: --frames must be >= 2 (the first frame is a warm-up), got {frames}")
    rows = []
    for spec, scene in _scenes(scenes):
        renderer = DeferredRenderer(scene)
        for w, h in sizes:
            server = QuasarServer(renderer, QuasarSettings(width=w, height=h, video=VideoSettings(crf=crf)))
            client = QuasarClient(w, h, ctx=renderer.ctx)
            per_frame, kinds = [], []
            for t, pose in tqdm(walk_poses(spec, scene, frames), desc=f"client {spec} {w}x{h}", unit="frame",
                                disable=quiet, leave=False):
                payload = server.encode(pose, t)
                client.receive(payload)
                client.render(pose)
                per_frame.append(dict(client.stats["ms"]))
                kinds.append(payload.stats["type"])
            server.close()
            ms = {k: float(np.mean([f[k] for f in per_frame[1:]])) for k in CLIENT_STAGES}
            row = {"scene": spec, "size": f"{w}x{h}", "frames": frames - 1,
                   "residual_frames": kinds[1:].count("residual"), **{f"{k}_ms": v for k, v in ms.items()},
                   "total_ms": float(sum(ms.values())), "cache_quads": int(client.stats["cache_quads"]),
                   "cache_bytes": int(client.stats["cache_bytes"]), "mesh_quads": int(client.stats["mesh_quads"])}
            rows.append(row)
            print(f"{spec:18s} {w}x{h:<5d} " + " ".join(f"{k} {ms[k]:7.1f}" for k in CLIENT_STAGES)
                  + f"  = {row['total_ms']:7.1f} ms/frame | cache {row['cache_quads']} quads "
                    f"{row['cache_bytes'] / 2**20:.2f} MiB, mesh {row['mesh_quads']} quads "
                    f"({row['residual_frames']}/{row['frames']} residual frames)", flush=True)
    return rows


def bench_stereo(scenes: list[str], size: tuple[int, int] = (960, 540), frames: int = 6, crf: float = 23.0,
                 quiet: bool = False) -> list[dict]:
    """YORO quality and cost ratio per scene and mode (see the module docstring)."""
    from tqdm import tqdm

    from quadcast.client.quasar import QuasarClient
    from quadcast.client.stereo import StereoSynthesizer, benchmark_stereo
    from quadcast.render.renderer import DeferredRenderer
    from quadcast.server.quasar import QuasarServer, QuasarSettings
    from quadcast.codec.encoder import VideoSettings
    from quadcast.sim.metrics import compare

    if frames < 2:
        raise ValueError(f"bench stereo: --frames must be >= 2 (the first frame is a warm-up), got {frames}")
    w, h = size
    rows = []
    for spec, scene in _scenes(scenes):
        renderer = DeferredRenderer(scene)
        server = QuasarServer(renderer, QuasarSettings(width=w, height=h, video=VideoSettings(crf=crf)))
        client = QuasarClient(w, h, ctx=renderer.ctx)
        acc: dict[str, list[dict]] = {"yoro": [], "rerender": []}
        poses = walk_poses(spec, scene, frames)
        for k, (t, pose) in enumerate(tqdm(poses, desc=f"stereo {spec} {w}x{h}", unit="frame", disable=quiet,
                                           leave=False)):
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
