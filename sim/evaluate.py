"""Evaluation: replay a trace for a method under simulated latency and score every shown frame against ground
truth (FLIP, SSIM, PSNR) — `quadcast eval`. Also scores a live client's recording (`evaluate_recording`).

Outputs in DIR: summary.json (means and figures; everything but the wall-clock `server_ms`/`client_ms` is
identical for the same seed), frames.csv (one row per scored frame), report.html (plots and worst frames).

Besides FLIP/SSIM/PSNR every scored frame has its *holes* (`quadcast.client.method.Coverage`): the fraction of the
display where the client showed no content of its own -- nothing drawn, or only smeared edge pixels (``holes`` =
``holes_empty`` + ``holes_smeared``; ``holes_interior`` is the part not touching the display's border: cracks and
disocclusions rather than what lies beyond the rendered frame); the summary has their mean/max and
``black_frames``, the display frames shown before the first payload plus the shown frames with no pixel drawn.

FLIP is reported over the whole frame (`flip`) and over the central 20 degrees around the gaze point (`flip_fovea`):
the view centre, or where a gaze trace (`gaze`, render/gaze.py) says the viewer looks at that display time. With a rate limit (`rate_mbit`, or a Mahimahi `rate_trace`), a rate controller (`adapt`,
`target_mbps` as its ceiling) or a fixed operating point (`point`), the summary also has `age_ms` (mean frame age
over every display tick: the display time minus the time the shown frame was predicted for), `age_bound_ms` (the
link latency plus two server frame intervals) and a `timeline`: every frame sent (time, bytes, arrival, operating
point, the controller's capacity estimate), every display tick (frame age, the shown frame's point) and the link's
capacity; report.html plots it. With a rate trace, `steps` lists the link's steps and how soon after each the
frame age was back under its bound for good (`recovered_s`).
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from quadcast.render.camera import Camera, Pose
from quadcast.render.renderer import DeferredRenderer
from quadcast.render.scene import load_scene, scene_trace
from quadcast.methods import make_client, make_server
from quadcast.protocol.frame import residual_to_reference_bytes
from quadcast.protocol.methods import MethodConfig
from quadcast.protocol.prediction import DEFAULT_PREDICTOR, PredictorSettings
from quadcast.protocol.pose import gaze_direction
from quadcast.protocol.rate import OperatingPoint, load_ladder, resolve_point, session_rate
from quadcast.sim.metrics import compare
from quadcast.sim.replay import DisplayedFrame, ReplayConfig, replay
from quadcast.sim.report import FrameImages, format_figure, write_frames_csv, write_report_html, write_summary_json

WALLCLOCK_KEYS = ("server_ms", "client_ms")
WORST_FRAMES = 3
FOVEA_RADIUS_DEG = 10.0
"""`flip_fovea` is FLIP over the pixels within this many degrees of the gaze point (the central 20 degrees)."""
MAX_SERVER_FRAME_MS = 10_000.0   # --server-frame-ms: a server slower than a frame in 10 s replays nothing useful


@dataclass
class EvalSpec:
    scene: str = "builtin:courtyard"
    trace: str = "builtin:walk"
    anchor: str | None = None      # re-anchor the trace into the scene: "spawn" or "x,y,z[,yaw_deg]"
    start: float = 0.0             # seconds into the trace where the replay starts
    method: str = "quasar"
    latency_ms: float = 20.0
    jitter_ms: float = 10.0
    rate_mbit: float | None = None
    loss: float = 0.0
    tcp: bool = False              # the downlink is one TCP stream: loss is of its segments, which are sent again
    queue_bytes: int | None = None  # with tcp: the drop-tail queue before the rate (None: it takes everything)
    viewcell_m: float = 0.5
    width: int = 960
    height: int = 540
    frames: int = 120              # client display frames (60 Hz)
    every: int = 1                 # score every K-th display frame
    stereo: bool = False
    seed: int = 0
    predict: bool = True
    predictor: PredictorSettings | None = None    # None: quadcast.protocol.prediction.DEFAULT_PREDICTOR
    crf: float | None = None       # None: the method's own (quadcast.protocol.methods.DEFAULT_CRF)
    chroma_qp_offset: int | None = None   # None: the method's own (quadcast.protocol.methods.DEFAULT_CHROMA_QP_OFFSET)
    reference_every: int = 5
    rate_trace: str | None = None  # a Mahimahi trace file or builtin:NAME for the downlink (instead of rate_mbit)
    adapt: bool = False            # the server's rate controller (quasar)
    target_mbps: float | None = None   # the controller's ceiling (implies adapt)
    point: str | OperatingPoint | None = None   # a fixed operating point: a ladder point's name or "key=value,..."
    ladder: str | None = None      # the ladder file (default: the measured one shipped with quadcast)
    gaze: str | None = None        # a gaze trace (render/gaze.py): foveation and flip_fovea around it, not the centre
    server_frame_ms: float = 0.0   # virtual time the server takes per frame (a live server's measured frame time
    #                                replays the rate it kept; 0: the server keeps the 30 Hz pose rate)


def _stats(values) -> dict:
    a = np.asarray([v for v in values if v is not None and np.isfinite(v)], np.float64)
    if a.size == 0:
        return {"mean": None, "std": None, "max": None}
    return {"mean": float(a.mean()), "std": float(a.std()), "max": float(a.max())}


def _mean_stages(rows: list[dict]) -> dict:
    keys = sorted({k for r in rows for k in r})
    return {k: float(np.mean([r[k] for r in rows if k in r])) for k in keys}


class _Scorer:
    """Ground truth at the client's true pose and time; FLIP/SSIM/PSNR; keeps the worst frames' images.

    Frames shown before the first payload arrived (``frame_id`` < 0) are black for every method: they are not
    scored (nor kept as worst frames)."""

    def __init__(self, renderer: DeferredRenderer, width: int, height: int, fovy: float, stereo=None, gaze=None):
        self.renderer, self.width, self.height, self.fovy = renderer, width, height, fovy
        self.gaze = gaze          # a GazeTrace, or None: the view centre
        self._view = Camera.perspective(Pose([0, 0, 0]), width, height, fovy)
        self.fovea = self._view.eccentricity_deg() <= FOVEA_RADIUS_DEG
        self.records: list[dict] = []
        self.worst: list[tuple[float, FrameImages]] = []
        self.stereo = stereo
        self.stereo_rows: list[dict] = []
        self.uncovered_frames = 0      # frames shown after a payload with no pixel drawn

    def count_coverage(self, frame_id: int, holes: float | None) -> None:
        """A shown frame's holes, for `black_frames` (frames before any payload are counted by the driver)."""
        if frame_id >= 0 and holes is not None and holes >= 1.0:
            self.uncovered_frames += 1

    @property
    def scored(self) -> list[dict]:
        return self.records

    @property
    def worst_images(self) -> list[FrameImages]:
        return [f for _, f in self.worst]

    def score(self, index: int, t: float, pose: Pose, image: np.ndarray, extra: dict,
              holes: np.ndarray | None = None, gaze_deg=None) -> None:
        """Score one shown frame; `holes` is its (H, W) hole mask when the client reported one; `gaze_deg` where the
        viewer looked (a live client's recorded gaze; else the scorer's gaze trace at `t`, else the view centre)."""
        if extra.get("frame_id", 0) < 0:
            return
        camera = Camera.perspective(pose, self.width, self.height, self.fovy)
        gt = self.renderer.render_color(camera, t)
        s = compare(gt, image)
        gaze = gaze_direction(gaze_deg) if gaze_deg is not None else \
            self.gaze.direction_at(t) if self.gaze is not None else None
        fovea = self.fovea if gaze is None else self._view.eccentricity_deg(gaze) <= FOVEA_RADIUS_DEG
        rec = {"frame": index, "t": t, "flip": s.flip, "flip_fovea": float(np.mean(s.flip_map[fovea])),
               "ssim": s.ssim, "psnr": s.psnr, **extra}
        self.records.append(rec)
        label = f"frame {index} (t={t:.2f} s) FLIP {s.flip:.3f}"
        if extra.get("holes") is not None:
            label += f", holes {100 * extra['holes']:.2f}%"
        if extra.get("pose_error_deg") is not None:
            label += f", pose error {extra['pose_error_deg']:.1f}° {extra['pose_error_cm']:.1f} cm"
        self.worst.append((s.flip, FrameImages(gt, image, s.flip_map, label, holes)))
        self.worst.sort(key=lambda x: -x[0])
        del self.worst[WORST_FRAMES:]
        if self.stereo is not None:
            self.stereo_rows.append(self.stereo(camera, t, image))


def run_eval(spec: EvalSpec, out: Path | None = None, quiet: bool = True) -> dict:
    """Replay and score one method on one trace; write the outputs to `out` when given. Returns the summary."""
    from tqdm import tqdm

    scene = load_scene(spec.scene)
    trace = scene_trace(spec.trace, scene, spec.anchor, spec.start)
    needed = spec.frames / 60.0
    if needed > trace.duration + 1e-6:        # a microsecond: traces keep their times in milliseconds, rounded
        after = f" after --start {spec.start:g} s" if spec.start else ""
        fit = int(np.floor((trace.duration + 1e-6) * 60.0))
        raise ValueError(f"trace {spec.trace!r} lasts {trace.duration:.3f} s{after}; {spec.frames} frames at 60 Hz "
                         f"need {needed:.3f} s (--frames {fit} fits)")
    if spec.every < 1 or spec.frames < 1:
        raise ValueError("--frames and --every must be >= 1")
    adapt = spec.adapt or spec.target_mbps is not None
    if (adapt or spec.point is not None) and spec.method != "quasar":
        raise ValueError(f"--adapt / --target-mbps / --point: operating points are quasar's knobs; the "
                         f"{spec.method} server has none")
    if adapt and spec.point is not None:
        raise ValueError("--point fixes the operating point; --adapt chooses it: give one of them")
    if spec.rate_trace is not None and spec.rate_mbit is not None:
        raise ValueError("--rate and --rate-trace both set the downlink's rate: give one of them")
    if not (np.isfinite(spec.server_frame_ms) and 0 <= spec.server_frame_ms <= MAX_SERVER_FRAME_MS):
        raise ValueError(f"--server-frame-ms: expected a time in [0, {MAX_SERVER_FRAME_MS:g}] ms, got "
                         f"{spec.server_frame_ms!r}")
    from quadcast.sim.ratetrace import resolve_rate_trace
    rate_trace = resolve_rate_trace(spec.rate_trace) if spec.rate_trace is not None else None
    ladder = load_ladder(spec.ladder) if adapt or isinstance(spec.point, str) else None
    from quadcast.render.gaze import GazeTrace
    gaze = GazeTrace.load(spec.gaze) if spec.gaze is not None else None
    point = resolve_point(spec.point, ladder) if spec.point is not None else None
    renderer = DeferredRenderer(scene)
    cfg = MethodConfig(width=spec.width, height=spec.height, viewcell_radius=spec.viewcell_m,
                       reference_every=spec.reference_every, crf=spec.crf, chroma_qp_offset=spec.chroma_qp_offset)
    server = make_server(spec.method, renderer, cfg)
    client = make_client(spec.method, cfg, renderer.ctx)
    predictor = spec.predictor or DEFAULT_PREDICTOR
    rc = ReplayConfig(latency_ms=spec.latency_ms, jitter_ms=spec.jitter_ms, rate_mbit=spec.rate_mbit,
                      loss=spec.loss, tcp=spec.tcp, queue_bytes=spec.queue_bytes, predict=spec.predict,
                      predictor=predictor, seed=spec.seed, rate_trace=rate_trace,
                      rate=session_rate(ladder, spec.target_mbps, spec.crf, spec.viewcell_m, spec.reference_every)
                      if adapt else None, point=point, gaze=gaze,
                      server_delay_ms=spec.server_frame_ms)
    stereo = _stereo_scorer(renderer, spec, client) if spec.stereo else None
    scorer = _Scorer(renderer, spec.width, spec.height, cfg.fovy_deg, stereo, gaze)
    bar = tqdm(total=spec.frames, desc=f"eval {spec.method}", unit="frame", disable=quiet, leave=False)
    client_ms: list[dict] = []

    def on_display(f: DisplayedFrame) -> None:
        extra = {"frame_id": f.frame_id, "age_ms": f.age_ms}
        if f.render_pose is not None:
            extra["pose_error_cm"] = f.render_pose.distance_to(f.pose) * 100
            extra["pose_error_deg"] = f.render_pose.angle_to_deg(f.pose)
        if f.coverage is not None:
            extra.update(f.coverage.figures())
        client_ms.append(f.client_ms)
        scorer.count_coverage(f.frame_id, extra.get("holes"))
        scorer.score(f.index, f.t, f.pose, f.image, extra, f.coverage.hole_mask if f.coverage is not None else None)

    def show(i: int) -> bool:
        bar.update(1)
        return i % spec.every == 0

    totals = replay(trace, server, client, rc, spec.frames, on_display, show)
    bar.close()
    server.close()
    client.close()
    rate = lambda b: b * 8 / totals.duration_s / 1e6  # noqa: E731
    c = totals.client
    run = {"latency_ms": spec.latency_ms, "jitter_ms": spec.jitter_ms, "rate_mbit": spec.rate_mbit,
           "loss": spec.loss, "tcp": spec.tcp, "queue_bytes": spec.queue_bytes, "viewcell_m": spec.viewcell_m,
           "display_frames": spec.frames, "every": spec.every,
           "seed": spec.seed, "predict": spec.predict, "server_frame_ms": spec.server_frame_ms,
           "predictor": str(predictor) if spec.predict else None, "mbps": rate(totals.bytes_total),
           "mbps_video": rate(totals.bytes_video), "mbps_geometry": rate(totals.bytes_geometry),
           "server_frames": totals.frames_sent, "frames_applied": c.frames_applied,
           "frames_lost": totals.frames_lost, "frames_rejected": c.frames_rejected,
           "frames_skipped": c.frames_skipped, "reference_requests": c.reference_requests,
           "frames_before_payload": totals.frames_before_payload,
           "server_ms": _mean_stages([stats.ms for _, _, stats in totals.payloads])}
    if spec.anchor is not None or spec.start:
        run.update(anchor=spec.anchor, start_s=spec.start)
    if spec.method == "quasar":
        run["residual_to_reference_bytes"] = residual_to_reference_bytes((kind, n) for kind, n, _ in totals.payloads)
    if rate_trace is not None or spec.rate_mbit is not None or adapt or point is not None:
        run.update(rate_run_figures(spec, totals, rc, point, scorer.records))
    summary = build_summary(spec.method, spec.scene, spec.trace, (spec.width, spec.height), scorer, client_ms, run)
    if out is not None:
        write_outputs(Path(out), summary, scorer.scored, scorer.worst_images)
    return summary


def rate_run_figures(spec: EvalSpec, totals, rc: ReplayConfig, point: OperatingPoint | None,
                     records: list[dict]) -> dict:
    """The summary's figures of a rate-limited or adaptive run (see the module docstring); adds each scored
    record's operating point (`point`, the ladder index of the frame shown) when there is a controller."""
    interval_ms = 1e3 / rc.server_hz
    ages = np.array([a for _, a, _ in totals.ages], np.float64)
    sent = totals.sent
    out = {"rate_trace": spec.rate_trace, "adapt": rc.rate is not None, "target_mbps": spec.target_mbps,
           "point": point.to_dict() if point is not None else None,
           "age_ms": float(np.nanmean(ages)) if np.isfinite(ages).any() else None,
           "age_bound_ms": spec.latency_ms + 2 * interval_ms,
           "frames_paced": totals.server.frames_paced}
    by_id = {f.frame_id: f for f in sent}
    timeline = {
        "sent": {"t": [f.t_sent for f in sent], "frame_id": [f.frame_id for f in sent],
                 "bytes": [f.bytes for f in sent], "t_arrive": [f.t_arrive for f in sent],
                 "point": [f.point_index for f in sent], "capacity_mbps": [f.capacity_mbps for f in sent],
                 "queue_delay_ms": [f.queue_delay_ms for f in sent]},
        "display": {"t": [t for t, _, _ in totals.ages], "age_ms": [a for _, a, _ in totals.ages],
                    "point": [by_id[i].point_index if i in by_id else None for _, _, i in totals.ages]},
    }
    end = totals.duration_s
    if rc.rate_trace is not None:
        t, mbps = rc.rate_trace.rate_mbit(0.0, end, 0.1)
        timeline["link"] = {"t": t.tolist(), "mbps": mbps.tolist()}
        out["steps"] = age_recovery(t, mbps, totals.ages, out["age_bound_ms"])
    elif rc.rate_mbit is not None:
        timeline["link"] = {"t": [0.0, end], "mbps": [rc.rate_mbit, rc.rate_mbit]}
    if rc.rate is not None:
        ladder, points = rc.rate.ladder, rc.rate.points
        timeline["points"] = [p.name for p in points]
        st = totals.rate
        out["rate_controller"] = {"decreases": st.decreases, "increases": st.increases,
                                  "final_point": points[st.index].name, "capacity_mbps": st.capacity_mbps,
                                  "ladder": ladder.command or "(unnamed)"}
        for r in records:
            f = by_id.get(r.get("frame_id"))
            r["point"] = f.point_index if f is not None else None
    out["timeline"] = timeline
    return out


def age_recovery(t: np.ndarray, mbps: np.ndarray, ages: list, bound_ms: float, ratio: float = 1.5,
                 window_s: float = 0.25) -> list[dict]:
    """The link's steps (its capacity per window `t`/`mbps` changing by more than `ratio` from one window to the
    next) and, for each, how soon after it the frame age was back under `bound_ms` for good (`recovered_s`: from
    then on to the next step, the mean age over every `window_s` -- a frame's age grows while it is shown, so a
    single display tick may pass the bound that the mean keeps) and the mean age from then on (`mean_age_ms`)."""
    edges = [i for i in range(1, len(mbps)) if max(mbps[i], mbps[i - 1]) > ratio * min(mbps[i], mbps[i - 1])]
    when = [float((t[i - 1] + t[i]) / 2) for i in edges]
    ticks = np.array([tt for tt, _, _ in ages])
    age = np.array([a for _, a, _ in ages], np.float64)
    steps = []
    for k, (i, at) in enumerate(zip(edges, when)):
        until = min(when[k + 1] if k + 1 < len(when) else math.inf, float(ticks[-1]) + 1e-9)
        starts = ticks[(ticks >= at) & (ticks + window_s <= until)]
        means = np.array([np.nanmean(age[(ticks >= s0) & (ticks < s0 + window_s)]) for s0 in starts])
        over = np.nonzero(~(means <= bound_ms))[0]
        recovered = (float(starts[over[-1]] - at) + (ticks[1] - ticks[0])) if over.size else 0.0
        if over.size and over[-1] == len(starts) - 1:
            recovered = float(until - at)              # not back under the bound before the next step
        after = (ticks >= at + recovered) & (ticks < until)
        steps.append({"t": at, "from_mbps": float(mbps[i - 1]), "to_mbps": float(mbps[i]), "recovered_s": recovered,
                      "mean_age_ms": float(np.nanmean(age[after])) if after.any() else None})
    return steps


def build_summary(method: str, scene: str, trace: str, size: tuple[int, int], scorer: "_Scorer",
                  client_ms: list[dict], run: dict) -> dict:
    """The one summary of a run, replayed or live: what was run, the scored frames' FLIP/SSIM/PSNR means and pose
    errors, the client's mean stage times, the synthesized eye's figures when there are any, and `run`'s figures
    (link, rates, frame counts), which win over the defaults here."""
    scored = scorer.scored
    mean = lambda key: float(np.mean([r[key] for r in scored])) if scored else None  # noqa: E731
    summary = {
        "method": method, "scene": scene, "trace": trace, "size": f"{size[0]}x{size[1]}",
        "latency_ms": None, "jitter_ms": None, "rate_mbit": None, "loss": None, "viewcell_m": None,
        "display_frames": None, "every": None, "mbps": None, "mbps_video": None, "mbps_geometry": None,
        "frames": len(scored), "flip": mean("flip"), "flip_fovea": mean("flip_fovea"), "ssim": mean("ssim"),
        "psnr": mean("psnr"),
        "pose_error_cm": _stats(r.get("pose_error_cm") for r in scored),
        "pose_error_deg": _stats(r.get("pose_error_deg") for r in scored),
        "holes": _stats(r.get("holes") for r in scored),
        "holes_empty": _stats(r.get("holes_empty") for r in scored)["mean"],
        "holes_smeared": _stats(r.get("holes_smeared") for r in scored)["mean"],
        "holes_interior": _stats(r.get("holes_interior") for r in scored)["mean"],
        "black_frames": (run.get("frames_before_payload") or 0) + scorer.uncovered_frames,
        "client_ms": _mean_stages(client_ms),
    }
    stereo_rows = [r for r in scorer.stereo_rows if r is not None]
    if stereo_rows:
        summary["stereo"] = stereo_summary(stereo_rows)
    summary.update(run)
    return summary


def write_outputs(out: Path, summary: dict, records: list[dict], worst: list) -> None:
    out.mkdir(parents=True, exist_ok=True)
    write_summary_json(out / "summary.json", summary)
    write_frames_csv(out / "frames.csv", records)
    write_report_html(out / "report.html", summary, records, worst,
                      title=f"quadcast {summary.get('method')} on {summary.get('trace')}")


def _stereo_scorer(renderer: DeferredRenderer, spec: EvalSpec, client):
    """`--stereo`: per scored frame, the client renders the left eye of the displayed head pose from its quad mesh
    and synthesizes the right eye with YORO (client.stereo, mode "yoro"). Returns, per frame: `ssim`, `psnr`,
    `flip` of the synthesized right eye against the ground-truth right eye (the deferred renderer at that eye's
    pose, IPD 63 mm), and `cost_ratio` = (left-eye render + synthesis) / (left-eye render + right-eye render), the
    right eye rendered from the same mesh and all stages timed GPU-finished (wall clock, so not seed-stable).
    Frames before the client has any payload give None (not scored)."""
    if not hasattr(client, "stereo_frame"):
        raise ValueError(f"--stereo: the {spec.method} client keeps no depth to synthesize an eye from; "
                         f"stereo works with the quasar and quadstream methods")

    def score(camera: Camera, t: float, image: np.ndarray) -> dict | None:
        if client.last_frame_id < 0:
            return None
        frame = client.stereo_frame(camera.pose, mode="yoro", with_rendered=True, masks=False)
        return score_stereo_eye(renderer, camera, t, frame.other_camera.pose, frame.synthesized, frame.cost_ratio)
    return score


def score_stereo_eye(renderer: DeferredRenderer, camera: Camera, t: float, eye_pose: Pose, synthesized: np.ndarray,
                     cost_ratio: float | None) -> dict:
    """One synthesized eye against ground truth (the deferred renderer at `camera` moved to `eye_pose`, time `t`):
    `ssim`, `psnr`, `flip`, and the frame's `cost_ratio` as given. Shared by `quadcast eval --stereo`
    (`_stereo_scorer`) and live recordings (`evaluate_recording`)."""
    truth = renderer.render_color(camera.with_pose(eye_pose), t)
    s = compare(truth, synthesized)
    return {"ssim": s.ssim, "psnr": s.psnr, "flip": s.flip, "cost_ratio": cost_ratio}


def stereo_summary(rows: list[dict]) -> dict | None:
    """The summary's `stereo` entry: the mean of each of `score_stereo_eye`'s figures (None without rows)."""
    if not rows:
        return None
    return {k: float(np.mean([r[k] for r in rows])) for k in ("ssim", "psnr", "flip", "cost_ratio")}


# ----------------------------------------------------------------------------------------------- sweep

SWEEP_METHODS = ("quasar", "quadstream", "meshwarp", "atw")
SWEEP_LATENCIES = ((20.0, 10.0), (50.0, 20.0))
SWEEP_VIEWCELLS = (0.25, 0.5, 1.0)


def run_sweep(base: EvalSpec, out: Path, methods=SWEEP_METHODS, latencies=SWEEP_LATENCIES,
              viewcells=SWEEP_VIEWCELLS, quiet: bool = False) -> list[dict]:
    """Methods × latencies × viewcells (viewcells matter only to quasar and quadstream)."""
    from tqdm import tqdm

    from quadcast.sim.report import plot_quality_vs_rate, write_comparison_table
    runs = []
    for method in methods:
        for lat, jit in latencies:
            for vc in (viewcells if method in ("quasar", "quadstream") else (base.viewcell_m,)):
                runs.append((method, lat, jit, vc))
    rows = []
    for method, lat, jit, vc in tqdm(runs, desc="sweep", unit="run", disable=quiet):
        spec = replace(base, method=method, latency_ms=lat, jitter_ms=jit, viewcell_m=vc)
        name = f"{method}_{lat:g}ms_{vc:g}m"
        s = run_eval(spec, out / name, quiet=True)
        rows.append({"method": method, "latency_ms": f"{lat:g}±{jit:g}",
                     "viewcell": vc if method in ("quasar", "quadstream") else "–",
                     "mbps": s["mbps"], "flip": s["flip"], "ssim": s["ssim"], "psnr": s["psnr"]})
    table = write_comparison_table(rows)
    (out / "table.md").write_text(table)
    (out / "sweep.json").write_text(json.dumps(rows, indent=1))
    plot_quality_vs_rate([r for r in rows if r["mbps"] and r["mbps"] > 0], out / "quality_vs_rate.png")
    return rows


# ------------------------------------------------------------------------------------- live recordings

def evaluate_recording(directory: str | Path) -> dict:
    """Score a live client's recording (recording.json + displayed PNGs) against ground truth rendered now.

    recording.json holds ``method``, ``scene``, ``trace``, ``size`` [w, h], ``fovy_deg``, ``frames`` (per recorded
    display frame: ``index``, ``t`` scene time, true ``position``/``quat``, ``image`` path relative to the
    directory, ``frame_id`` of the newest applied server frame or -1, and optional ``age_ms``,
    ``pose_error_cm``/``pose_error_deg``, ``client_ms``, ``gaze_deg`` (where the viewer looked: ``flip_fovea``
    centres on it), and with stereo a ``stereo`` entry: ``right`` image path
    of the synthesized eye, that eye's ``position``/``quat`` and the frame's ``cost_ratio``) and an optional
    ``summary`` of run-wide figures (Mbps on the socket, frame counts, ...), which is merged into the summary.
    Frames may carry the client's ``holes``/``holes_empty``/``holes_smeared`` and the summary
    ``frames_before_payload`` (display frames shown before the first payload), which make ``holes`` and
    ``black_frames`` as in ``quadcast eval``.
    Writes summary.json (the fields of ``quadcast eval`` plus ``live``, and ``stereo`` as ``quadcast eval
    --stereo`` has it when the frames have stereo entries), frames.csv and report.html to the directory and
    returns the summary.
    """
    from PIL import Image

    directory = Path(directory)
    rec = json.loads((directory / "recording.json").read_text())
    w, h = rec["size"]
    renderer = DeferredRenderer(load_scene(rec["scene"]))
    scorer = _Scorer(renderer, w, h, rec.get("fovy_deg", 60.0))
    client_ms = []

    def load(name: str) -> np.ndarray:
        image = np.asarray(Image.open(directory / name).convert("RGB"))
        if image.shape[:2] != (h, w):
            raise ValueError(f"{name}: image is {image.shape[1]}x{image.shape[0]}, recording says {w}x{h}")
        return image
    for f in rec["frames"]:
        if f.get("frame_id", 0) < 0:
            continue   # shown before the first payload arrived: black for every method, not scored
        image = load(f["image"])
        pose = Pose(f["position"], f["quat"])
        extra = {k: f[k] for k in ("frame_id", "age_ms", "pose_error_cm", "pose_error_deg", "bytes_video",
                                   "bytes_geometry", "holes", "holes_empty", "holes_smeared", "holes_interior")
                 if k in f}
        scorer.count_coverage(extra["frame_id"] if "frame_id" in extra else 0, extra.get("holes"))
        scorer.score(f["index"], f["t"], pose, image, extra, gaze_deg=f.get("gaze_deg"))
        client_ms.append(f.get("client_ms", {}))
        eye = f.get("stereo")
        if eye is not None:
            if eye.get("cost_ratio") is None:
                raise ValueError(f"frame {f['index']}: stereo entry has no cost_ratio")
            camera = Camera.perspective(pose, w, h, rec.get("fovy_deg", 60.0))
            scorer.stereo_rows.append(score_stereo_eye(renderer, camera, f["t"], Pose(eye["position"], eye["quat"]),
                                                       load(eye["right"]), float(eye["cost_ratio"])))
    run = {"viewcell_m": rec.get("viewcell_m"), "mbps": rec.get("mbps"), **rec.get("summary", {}), "live": True}
    summary = build_summary(rec["method"], rec["scene"], rec.get("trace"), (w, h), scorer, client_ms, run)
    write_outputs(directory, summary, scorer.scored, scorer.worst_images)
    return summary


def strip_wallclock(summary: dict) -> dict:
    """The summary without its wall-clock figures (what must be identical for the same seed): the per-stage ms
    and the stereo cost ratio, which is a ratio of measured times."""
    out = {k: v for k, v in summary.items() if k not in WALLCLOCK_KEYS}
    if isinstance(out.get("stereo"), dict):
        out["stereo"] = {k: v for k, v in out["stereo"].items() if k != "cost_ratio"}
    return out


def format_summary(s: dict) -> str:
    f = format_figure
    return (f"{s['method']:>11s} {s.get('latency_ms', 0):>4g}±{s.get('jitter_ms', 0):<3g}ms vc {s['viewcell_m']:g} m: "
            f"{f(s['mbps'], '8.2f')} Mbps (video {f(s.get('mbps_video'), '.2f')}, geometry "
            f"{f(s.get('mbps_geometry'), '.2f')})  FLIP {f(s['flip'], '.4f')} (fovea {f(s.get('flip_fovea'), '.4f')})"
            f"  SSIM {f(s['ssim'], '.4f')}  PSNR {f(s['psnr'], '.2f')} dB  holes {f(_pct((s.get('holes') or {}).get('mean')), '.2f')}% "
            f"(max {f(_pct((s.get('holes') or {}).get('max')), '.1f')}%), {s.get('black_frames', 0)} black frames"
            + (f"  frame age {f(s['age_ms'], '.1f')} ms (bound {f(s.get('age_bound_ms'), '.1f')})"
               if s.get("age_ms") is not None else ""))


def _pct(fraction: float | None) -> float | None:
    return None if fraction is None else 100 * fraction
