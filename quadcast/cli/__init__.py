"""The `quadcast` command line: one program, one subcommand per job.

    quadcast render   --scene S --trace T [--anchor A] [--start S] --size WxH --frames N [--every K] --out DIR [--depth]
    quadcast encode   --scene S --trace T --size WxH --frames N --viewcell R [--every K] --out DIR
    quadcast predict  --trace T [--trace T2] [--start S --duration D] --latency 20,50 --jitter 10,20 [--seeds N]
    quadcast eval     --scene S --trace T [--anchor A] [--start S] --method M --latency MS --jitter MS --viewcell R
                      --size WxH --out DIR
    quadcast eval     --sweep --size WxH [--frames N] [--every K] --out DIR
    quadcast bench    server|client|stereo|render|browser [--sizes 960x540,1920x1080] [--scenes builtin:courtyard,monastery]
    quadcast server   --port P [--method quasar] [--transport tcp|webrtc] [--host 127.0.0.1] [--token T]
    quadcast link     --listen P --to HOST:PORT --delay 20ms --jitter 10ms [--rate 200mbit] [--loss 0.5%]
    quadcast client   --connect HOST:PORT --trace T [--size WxH] [--duration S] [--transport tcp|webrtc] --out DIR
    quadcast demo     [--out DIR] [--transport tcp|webrtc]

Each subcommand's --help says more. Errors in the user's input print one line naming what was wrong and exit 2.

A trace recorded elsewhere (QUASAR's format) replays in any scene with ``--anchor spawn`` (the scene's spawn
point) or ``--anchor x,y,z[,yaw_deg]``: its pose at ``--start`` goes there and the rest keeps its motion
relative to that pose.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np


def _progress(iterable, total=None, desc=None, quiet=False):
    from tqdm import tqdm
    return tqdm(iterable, total=total, desc=desc, disable=quiet, unit="frame", leave=False, file=sys.stderr)


# ------------------------------------------------------------------------------------------------ render

def render_trace(scene_spec: str, trace_spec: str, size: tuple[int, int], frames: int, every: int, out: Path,
                 depth: bool = False, fovy: float = 60.0, quiet: bool = False, anchor: str | None = None,
                 start: float = 0.0) -> list[Path]:
    """Render ground-truth frames along a trace (re-anchored and cut as `quadcast.render.scene.scene_trace`
    does): frame i is the trace pose at sample i*every. Returns PNG paths."""
    from PIL import Image

    from quadcast.render.camera import Camera, Pose
    from quadcast.render.renderer import DeferredRenderer
    from quadcast.render.scene import load_scene, scene_trace

    scene = load_scene(scene_spec)
    trace = scene_trace(trace_spec, scene, anchor, start)
    if frames < 1 or every < 1:
        raise ValueError(f"--frames and --every must be >= 1, got {frames} and {every}")
    indices = [i * every for i in range(frames)]
    if indices[-1] >= len(trace):
        raise ValueError(f"trace {trace.name!r} has {len(trace)} poses; {frames} frames every {every} need "
                         f"{indices[-1] + 1}")
    renderer = DeferredRenderer(scene)
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for n, i in enumerate(_progress(indices, desc="render", quiet=quiet)):
        t = float(trace.times[i] - trace.times[0])
        camera = Camera.perspective(Pose(trace.positions[i], trace.quats[i]), *size, fovy_deg=fovy)
        frame = renderer.render(camera, t)
        path = out / f"frame_{n:05d}.png"
        Image.fromarray(frame.color).save(path)
        if depth:
            np.save(out / f"depth_{n:05d}.npy", frame.depth)
        paths.append(path)
    contact_sheet(paths, out / "contact_sheet.png")
    return paths


def contact_sheet(paths: list[Path], out: Path, columns: int = 5, thumb_width: int = 320) -> Path:
    """Tile PNGs into one overview image."""
    from PIL import Image
    images = [Image.open(p) for p in paths]
    if not images:
        raise ValueError("contact sheet: no images")
    w = min(thumb_width, images[0].width)
    h = round(images[0].height * w / images[0].width)
    cols = min(columns, len(images))
    rows = (len(images) + cols - 1) // cols
    sheet = Image.new("RGB", (cols * w, rows * h))
    for k, img in enumerate(images):
        sheet.paste(img.convert("RGB").resize((w, h)), ((k % cols) * w, (k // cols) * h))
    sheet.save(out)
    return out


def cmd_render(args) -> int:
    from quadcast.render.camera import parse_size
    paths = render_trace(args.scene, args.trace, parse_size(args.size), args.frames, args.every, Path(args.out),
                         depth=args.depth, fovy=args.fovy, quiet=args.quiet, anchor=args.anchor, start=args.start)
    print(f"wrote {len(paths)} frames and contact_sheet.png to {args.out}")
    return 0


# ------------------------------------------------------------------------------------------------ encode

def cmd_encode(args) -> int:
    from quadcast.render.camera import parse_size
    from quadcast.sim.encode import encode_trace
    stats = encode_trace(args.scene, args.trace, parse_size(args.size), args.frames, args.viewcell, args.every,
                         Path(args.out), layers=args.layers, crf=args.crf, quiet=args.quiet)
    ratio = stats["residual_to_reference_bytes"]
    print(f"{len(stats['frames'])} frames -> {args.out}: {stats['mbps_at_30fps']:.2f} Mbps at 30 fps, "
          f"residual/reference bytes {ratio:.3f}" if ratio is not None else "(no residual frames)")
    print("mean ms per stage: " + ", ".join(f"{k} {v:.1f}" for k, v in stats["mean_ms"].items()))
    return 0


# ------------------------------------------------------------------------------------------ predict, eval

def cmd_predict(args) -> int:
    """Pose-prediction error along each trace at each link latency, without and with prediction (mean over
    --seeds jitter draws), and the overshoot bound of `quadcast.sim.prediction`."""
    from quadcast.render.scene import load_scene, scene_trace
    from quadcast.render.traces import SPAWN
    from quadcast.sim.prediction import prediction_errors
    latencies = _float_list(args.latency, "--latency")
    jitters = _float_list(args.jitter, "--jitter")
    if len(jitters) == 1:
        jitters *= len(latencies)
    if len(jitters) != len(latencies):
        raise ValueError(f"--jitter: give one value or one per --latency ({len(latencies)}), got {len(jitters)}")
    if args.seeds < 1:
        raise ValueError(f"--seeds must be >= 1, got {args.seeds}")
    scene = load_scene(args.scene) if args.anchor is not None and args.anchor.strip() == SPAWN else None
    rows = []
    print(f"{'trace':24s} {'link':>7s} {'horizon':>8s} | {'position cm: none':>17s} {'predicted':>9s} {'ratio':>5s} | "
          f"{'rotation °: none':>16s} {'predicted':>9s} {'ratio':>5s} | {'max ° none/pred':>15s} | bound")
    for spec in args.trace or ["builtin:walk"]:
        trace = scene_trace(spec, scene, args.anchor, args.start, args.duration)
        for lat, jit in zip(latencies, jitters):
            runs = {mode: [prediction_errors(trace.times, trace.positions, trace.quats, lat, jit, predict=mode,
                                             seed=args.seed + k) for k in range(args.seeds)] for mode in (False, True)}

            def mean(mode, part, stat="mean"):
                return float(np.mean([r[part][stat] for r in runs[mode]]))

            def worst(mode, part):
                return float(np.max([r[part]["max"] for r in runs[mode]]))
            row = {"trace": spec, "latency_ms": lat, "jitter_ms": jit, "seeds": args.seeds,
                   "horizon_ms": mean(True, "horizon_ms"),
                   "none": {part: {"mean": mean(False, part), "std": mean(False, part, "std"),
                                    "max": worst(False, part)} for part in ("position_cm", "rotation_deg")},
                   "predicted": {part: {"mean": mean(True, part), "std": mean(True, part, "std"),
                                         "max": worst(True, part)} for part in ("position_cm", "rotation_deg")},
                   "bound_violations": int(sum(r["bound"]["violations"] for r in runs[True])),
                   "frames": int(sum(r["samples"] for r in runs[True]))}
            rows.append(row)
            n, p = row["none"], row["predicted"]
            print(f"{Path(spec).stem[:24]:24s} {lat:>3g}±{jit:<3g} {row['horizon_ms']:6.1f}ms | "
                  f"{n['position_cm']['mean']:17.2f} {p['position_cm']['mean']:9.2f} "
                  f"{p['position_cm']['mean'] / n['position_cm']['mean']:5.2f} | "
                  f"{n['rotation_deg']['mean']:16.2f} {p['rotation_deg']['mean']:9.2f} "
                  f"{p['rotation_deg']['mean'] / n['rotation_deg']['mean']:5.2f} | "
                  f"{n['rotation_deg']['max']:7.1f}/{p['rotation_deg']['max']:<7.1f} | "
                  f"{row['bound_violations']}/{row['frames']} over", flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))
    return 0


def _float_list(text: str, option: str) -> list[float]:
    try:
        values = [float(v) for v in str(text).split(",") if v.strip()]
    except ValueError:
        raise ValueError(f"{option}: expected numbers separated by commas, got {text!r}") from None
    if not values or not all(np.isfinite(v) and v >= 0 for v in values):
        raise ValueError(f"{option}: expected finite numbers >= 0, got {text!r}")
    return values


def _client_nice(text: str) -> int:
    """argparse type of ``demo --client-nice``: an integer 0..19."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not an integer: {text!r}") from None
    if not 0 <= value <= 19:
        raise argparse.ArgumentTypeError(f"must be 0..19 (a niceness increment), got {value}")
    return value


def _trace_start(text: str) -> float | str:
    """argparse type of ``--start`` where it may be ``fastest`` (demo, eval): seconds, or ``fastest``."""
    if text.strip().lower() == "fastest":
        return "fastest"
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not seconds or 'fastest': {text!r}") from None


def _client_cores(text: str) -> int:
    """argparse type of ``demo --client-cores``: an integer >= 0."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not an integer: {text!r}") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be >= 0 (0: all cores), got {value}")
    return value


def _eval_spec(args):
    from quadcast.render.camera import parse_size
    from quadcast.sim.evaluate import EvalSpec
    from quadcast.sim.link import parse_bytes, parse_loss, parse_rate_mbit
    w, h = parse_size(args.size)
    if args.queue and not args.tcp:
        raise ValueError("--queue is the TCP downlink's queue: give --tcp too")
    start = args.start
    if start == "fastest":
        from quadcast.render.traces import resolve_trace
        trace = resolve_trace(args.trace)
        window = min(args.frames / 60.0, trace.duration)   # the replay's display frames at 60 Hz, or the whole trace
        start = trace.fastest_window(window)
        print(f"eval: the fastest {window:g} s of {args.trace} start at {start:.2f} s (--start {start})", flush=True)
    return EvalSpec(scene=args.scene, trace=args.trace, anchor=args.anchor, start=start, method=args.method,
                    latency_ms=args.latency,
                    jitter_ms=args.jitter, rate_mbit=parse_rate_mbit(args.rate) if args.rate else None,
                    loss=parse_loss(args.loss) if args.loss else 0.0, tcp=args.tcp,
                    queue_bytes=parse_bytes(args.queue) if args.queue else None, viewcell_m=args.viewcell,
                    width=w, height=h,
                    frames=args.frames, every=args.every, stereo=args.stereo, seed=args.seed,
                    predict=not args.no_predict, crf=args.crf, chroma_qp_offset=args.chroma_qp_offset,
                    rate_trace=args.rate_trace, adapt=args.adapt,
                    target_mbps=args.target_mbps, point=args.point, ladder=args.ladder, gaze=args.gaze,
                    server_frame_ms=args.server_frame_ms)


def cmd_eval(args) -> int:
    from quadcast.sim.evaluate import format_summary, run_eval, run_sweep
    spec = _eval_spec(args)
    out = Path(args.out)
    if args.sweep:
        rows = run_sweep(spec, out, quiet=args.quiet)
        print((out / "table.md").read_text(), end="")
        print(f"sweep of {len(rows)} runs -> {out}/table.md, {out}/quality_vs_rate.png")
        return 0
    summary = run_eval(spec, out, quiet=args.quiet)
    print(format_summary(summary))
    if "stereo" in summary:
        st = summary["stereo"]
        print(f"stereo (synthesized eye): SSIM {st['ssim']:.4f} PSNR {st['psnr']:.2f} dB FLIP {st['flip']:.4f}, "
              f"cost {100 * st['cost_ratio']:.1f}% of two renders")
    print(f"report: {out / 'report.html'}")
    return 0


# ------------------------------------------------------------------------------------------------- bench

def parser_default_sizes() -> str:
    return "960x540,1920x1080"


def cmd_bench(args) -> int:
    from quadcast.render.camera import parse_size
    from quadcast.cli import bench
    if args.what == "quality":
        return _bench_quality(args)
    if args.traces and args.what != "ladder":
        raise ValueError(f"bench {args.what}: trace files are for 'bench quality' and 'bench ladder' only")
    sizes = [parse_size(s) for s in args.sizes.split(",")]
    scenes = args.scenes.split(",")
    frames_given = args.frames
    args.frames = 10 if args.frames is None else args.frames
    if args.what == "render":
        rows = bench.bench_render(scenes, sizes, args.frames)
    elif args.what == "server":
        rows = bench.bench_server(scenes, sizes, args.frames, quiet=args.quiet)
    elif args.what == "client":
        rows = bench.bench_client(scenes, sizes, args.frames, quiet=args.quiet)
    elif args.what == "stereo":
        rows = bench.bench_stereo(scenes, sizes[0], args.frames, quiet=args.quiet)
    elif args.what == "ladder":
        size = sizes[0] if args.sizes != parser_default_sizes() else (640, 360)
        rows = bench.bench_ladder(args.traces or None, size, 48 if frames_given is None else frames_given,
                                  out=Path(args.out) if args.out else None, write=args.write,
                                  command="quadcast " + " ".join(sys.argv[1:]), quiet=args.quiet)
    elif args.what == "browser":
        from quadcast.cli.browser import bench_browser, chromium_missing
        if (missing := chromium_missing()) is not None:
            raise ValueError(f"bench browser: {missing}")
        rows = bench_browser(sizes, scenes[0], duration=args.seconds, trace=args.trace,
                             screenshot=Path(args.screenshot) if args.screenshot else None)
    else:
        raise ValueError(f"unknown benchmark {args.what!r}")
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=2))
    return 0


def _bench_quality(args) -> int:
    from quadcast.cli import bench
    from quadcast.protocol.methods import check_method
    from quadcast.render.camera import parse_size
    methods = [m.strip() for m in (args.methods or ",".join(bench.QUALITY_METHODS)).split(",") if m.strip()]
    for m in methods:
        check_method(m)
    latencies = []
    for item in (args.latencies or "20x10,50x20").split(","):
        lat, sep, jit = item.strip().partition("x")
        values = _float_list(f"{lat},{jit or 0}", "--latencies")
        latencies.append((values[0], values[1]))
    size = parse_size(args.size or "640x360")
    scenes = [s.strip() for s in args.scenes.split(",") if s.strip()]
    if args.every < 1 or (args.frames is not None and args.frames < 1):
        raise ValueError("--frames and --every must be >= 1")
    rows = bench.bench_quality(args.traces, scenes, methods, latencies, size, args.frames, args.every,
                               args.viewcell, out=Path(args.out) if args.out else None, quiet=args.quiet)
    if rows:
        print()
        print(bench.format_quality_table(rows), end="")
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=2))
    return 0


# -------------------------------------------------------------------------------------------------- demo

def cmd_demo(args) -> int:
    """The live system (by default on the built-in scene and walk): server, link (20±10 ms) and client as three
    processes on loopback."""
    from quadcast.cli.demo import CLIENT_CORES, CLIENT_NICE, DemoView, run_demo
    nice = CLIENT_NICE if args.client_nice is None else args.client_nice
    cores = CLIENT_CORES if args.client_cores is None else args.client_cores
    view = DemoView(scene=args.scene, trace=args.trace, anchor=args.anchor, start=args.start, duration=args.duration,
                    size=args.size)
    return run_demo(Path(args.out), quiet=args.quiet, view=view, compare=not args.no_compare, client_nice=nice,
                    client_cores=cores, warm_up=not args.no_warm_up, transport=args.transport)


# -------------------------------------------------------------------------------------------------- main

def add_trace_placement(p: argparse.ArgumentParser, start: bool = True, fastest: str | None = None) -> None:
    """``--anchor`` (and ``--start``) of the commands that follow a trace; with `fastest` (the window it is taken
    over, for the help), ``--start`` may also be ``fastest``."""
    p.add_argument("--anchor", help="re-anchor the trace into the scene: 'spawn' (the scene's spawn point) or "
                                    "'x,y,z[,yaw_deg]'; its pose at --start goes there, its motion stays relative")
    if start and fastest:
        p.add_argument("--start", type=_trace_start, default=0.0,
                       help=f"trace time to start at, seconds, or 'fastest': the start of the trace's fastest motion "
                            f"over {fastest}")
    elif start:
        p.add_argument("--start", type=float, default=0.0, help="trace time to start at, seconds")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="quadcast", description=__doc__.split("\n\n")[0])
    parser.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    sub = parser.add_subparsers(dest="command", required=True)
    from quadcast.cli.live import add_live_commands, video_option_help
    from quadcast.protocol.methods import method_crf

    p = sub.add_parser("render", help="render ground-truth frames along a camera trace")
    p.add_argument("--scene", default="builtin:courtyard")
    p.add_argument("--trace", default="builtin:walk")
    add_trace_placement(p)
    p.add_argument("--size", default="960x540", help="WxH")
    p.add_argument("--frames", type=int, default=10)
    p.add_argument("--every", type=int, default=1, help="use every K-th pose of the trace")
    p.add_argument("--fovy", type=float, default=60.0, help="vertical field of view, degrees")
    p.add_argument("--depth", action="store_true", help="also write linear depth as depth_NNNNN.npy")
    p.add_argument("--out", required=True)
    p.set_defaults(func=cmd_render)

    p = sub.add_parser("encode", help="run the QUASAR server along a trace and write its payloads and stats")
    p.add_argument("--scene", default="builtin:courtyard")
    p.add_argument("--trace", default="builtin:walk")
    p.add_argument("--size", default="960x540", help="WxH")
    p.add_argument("--frames", type=int, default=30)
    p.add_argument("--viewcell", type=float, default=0.5, help="view-sphere radius, metres")
    p.add_argument("--every", type=int, default=5, help="a reference frame at least every K frames")
    p.add_argument("--layers", type=int, default=4, help="k: visible + k-1 hidden layers")
    p.add_argument("--crf", type=float,
                   help=f"x264 constant rate factor (default: quasar's own, {method_crf('quasar', None):g})")
    p.add_argument("--out", required=True)
    p.set_defaults(func=cmd_encode)

    p = sub.add_parser("predict", help="pose-prediction errors along traces, without and with prediction (QUASAR "
                                       "Table 1)")
    p.add_argument("--trace", action="append", help="a trace (repeat for several; default builtin:walk)")
    p.add_argument("--scene", default="builtin:courtyard", help="scene whose spawn point --anchor spawn uses")
    add_trace_placement(p)
    p.add_argument("--duration", type=float, help="seconds of the trace from --start (default: to its end)")
    p.add_argument("--latency", default="20", help="one-way latency, ms; several comma-separated (e.g. 20,50)")
    p.add_argument("--jitter", default="10", help="uniform jitter, +- ms; one, or one per latency (e.g. 10,20)")
    p.add_argument("--seed", type=int, default=0, help="first jitter seed")
    p.add_argument("--seeds", type=int, default=1, help="jitter draws averaged per row")
    p.add_argument("--json", help="also write the rows to this JSON file")
    p.set_defaults(func=cmd_predict)

    p = sub.add_parser("eval", help="replay a trace under simulated latency; Mbps and FLIP/SSIM/PSNR per trace")
    p.add_argument("--scene", default="builtin:courtyard")
    p.add_argument("--trace", default="builtin:walk")
    add_trace_placement(p, fastest="the replay's --frames at 60 Hz")
    p.add_argument("--method", default="quasar", choices=["quasar", "quadstream", "meshwarp", "meshwarp120", "atw"])
    p.add_argument("--latency", type=float, default=20.0, help="one-way latency, ms")
    p.add_argument("--jitter", type=float, default=10.0, help="uniform jitter, +- ms")
    p.add_argument("--rate", help="downlink rate cap, e.g. 200mbit")
    p.add_argument("--rate-trace", help="downlink capacity over time: a Mahimahi trace file (one line per 1500-byte "
                                        "delivery opportunity, ms) or builtin:const-20|step-100-15-100|sawtooth-10-40")
    p.add_argument("--adapt", action="store_true",
                   help="the server's rate controller picks each frame's operating point from the client's receive "
                        "reports: the ladder's, or the server's own settings after 2 s of calm at its best (quasar)")
    p.add_argument("--target-mbps", type=float, help="the rate controller's ceiling, Mbit/s (implies --adapt)")
    p.add_argument("--point", help="a fixed operating point: a ladder point's name or key=value,... (crf, quad, "
                                   "coarse, viewcell, hidden, every, fovea, sigma, gamma, max, atlas)")
    p.add_argument("--ladder", help="the operating points' ladder file (default: the measured one shipped)")
    p.add_argument("--gaze", help="a gaze trace ('t_ms x_deg y_deg' per line, angles from the view axis): foveated "
                                  "points and FLIP over the central 20 degrees follow it (default: the view centre)")
    p.add_argument("--loss", help="downlink loss, e.g. 0.5%%: of whole messages, or with --tcp of TCP segments")
    p.add_argument("--tcp", action="store_true",
                   help="the downlink is one TCP stream, as `quadcast link` models it: --loss is of its segments, "
                        "which are sent again a round trip later, and a Reno window paces it")
    p.add_argument("--queue", help="with --tcp: the drop-tail queue before --rate, e.g. 64k (default: it takes "
                                   "everything); a segment that overflows it is lost and sent again")
    p.add_argument("--server-frame-ms", type=float, default=0.0,
                   help="virtual time the server takes per frame (e.g. a live server's measured frame time, to "
                        "replay the frame rate it kept; default 0: it keeps the 30 Hz pose rate)")
    p.add_argument("--viewcell", type=float, default=0.5, help="view-sphere radius, metres")
    p.add_argument("--size", default="960x540", help="WxH")
    p.add_argument("--frames", type=int, default=120, help="client display frames at 60 Hz")
    p.add_argument("--every", type=int, default=1, help="score every K-th display frame")
    p.add_argument("--stereo", action="store_true", help="also synthesize and score the second eye (YORO)")
    p.add_argument("--no-predict", action="store_true")
    p.add_argument("--crf", type=float, help=video_option_help("crf"))
    p.add_argument("--chroma-qp-offset", type=int, help=video_option_help("chroma_qp_offset"))
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--sweep", action="store_true",
                   help="methods x {20+-10, 50+-20 ms} x viewcell {0.25, 0.5, 1.0}: a comparison table and plot")
    p.add_argument("--out", required=True)
    p.set_defaults(func=cmd_eval)

    p = sub.add_parser("bench", help="print speed figures (not a test); 'quality': quality under real head motion; "
                                     "'ladder': the rate controller's operating points")
    p.add_argument("what", choices=["server", "render", "client", "stereo", "browser", "quality", "ladder"],
                   help="stereo (YORO quality and cost ratio) runs at the first of --sizes; browser (the viewer page "
                        "in headless Chromium against a live server on loopback: fps, frame age) on the first of "
                        "--scenes; quality replays real head traces (default: ../shared/traces/*.txt) in each scene "
                        "for every method")
    p.add_argument("traces", nargs="*", help="quality, ladder: QUASAR-format head trace files")
    p.add_argument("--scenes", default="builtin:courtyard,monastery")
    p.add_argument("--sizes", default=parser_default_sizes(), help="(ladder: 640x360 unless given)")
    p.add_argument("--frames", type=int, help="frames per run (default 10; quality: display frames, default 240 = "
                                              "the 4 s window at 60 Hz; ladder: display frames per run, 48)")
    p.add_argument("--json", help="also write the figures to this JSON file")
    p.add_argument("--seconds", type=float, default=20.0, help="browser: measuring time per size")
    p.add_argument("--screenshot", help="browser: save a screenshot of the page (last size) to this PNG")
    p.add_argument("--trace", default="builtin:walk", help="browser: the built-in trace the page follows")
    p.add_argument("--methods", help="quality: methods, comma-separated (default all five)")
    p.add_argument("--latencies", help="quality: one-way latency x jitter in ms, comma-separated (default 20x10,50x20)")
    p.add_argument("--size", help="quality: WxH (default 640x360)")
    p.add_argument("--every", type=int, default=8, help="quality: score every K-th display frame")
    p.add_argument("--viewcell", type=float, default=0.5, help="quality: view-cell radius, metres")
    p.add_argument("--out", help="quality: keep every run's summary, frames.csv and report.html under this folder; "
                                 "ladder: output directory (default out/ladder)")
    p.add_argument("--write", help="ladder: also write the Pareto front as this ladder file (the controller's: "
                                   "protocol/ladder.json)")
    p.set_defaults(func=cmd_bench)

    p = sub.add_parser("demo", help="the live system (by default the built-in walk through the built-in scene): "
                                    "server, link (20±10 ms) and client processes on loopback; prints Mbps and "
                                    "FLIP/SSIM, then the same in virtual time")
    p.add_argument("--out", default="out/demo")
    p.add_argument("--no-compare", action="store_true",
                   help="skip the same trace in virtual time afterwards (its FLIP is what the live run is held to)")
    p.add_argument("--scene", default="builtin:courtyard", help="the scene the server renders")
    p.add_argument("--trace", default="builtin:walk", help="the trace the client follows (builtin:NAME or a QUASAR "
                                                           "trace file)")
    add_trace_placement(p, fastest="--duration s")
    p.add_argument("--duration", type=float, help="seconds live (default: 10, or the rest of the trace if shorter)")
    p.add_argument("--size", default="480x270", help="WxH")
    p.add_argument("--client-nice", type=_client_nice, default=None, metavar="N",
                   help="run the client N below the server's and link's priority, 0..19 (default 19: a headset has "
                        "its own processor; here the client shares the server's cores)")
    p.add_argument("--client-cores", type=_client_cores, default=None, metavar="N",
                   help="run the client on the last N of the machine's cores, 0 for all of them (default 1: it "
                        "never takes every core from the server)")
    p.add_argument("--no-warm-up", action="store_true",
                   help="neither the server's spare workers nor the client run made-up frames first (so that "
                        "llvmpipe compiles the shaders before the session's first frames need them)")
    p.add_argument("--transport", choices=("tcp", "webrtc"), default="tcp",
                   help="what server, link and client speak (webrtc: the link shapes every datagram between the "
                        "peers; the virtual-time replays are the same either way)")
    p.set_defaults(func=cmd_demo)

    add_live_commands(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    from quadcast.render.gl import GLUnavailableError
    from quadcast.render.scene import SceneError
    from quadcast.render.traces import TraceError
    try:
        return args.func(args)
    except (ValueError, SceneError, TraceError, GLUnavailableError, FileNotFoundError) as exc:  # RateTraceError,
        # LadderError are ValueErrors
        print(f"quadcast {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
