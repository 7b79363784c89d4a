"""Replay in virtual time and the evaluation outputs (QUASAR §4.1.3)."""
import csv
import json
import re

import numpy as np
import pytest

from quadcast.render.traces import TraceError, resolve_trace
from quadcast.sim.evaluate import EvalSpec, WALLCLOCK_KEYS, run_eval, run_sweep, strip_wallclock

TINY = dict(scene="builtin:courtyard", trace="builtin:walk", width=160, height=96, frames=12, every=3)


def test_zero_latency_static_scene_quasar_is_faithful(tmp_path):
    spec = EvalSpec(scene="builtin:courtyard-static", trace="builtin:static", method="quasar", latency_ms=0,
                    jitter_ms=0, width=320, height=180, frames=8, every=2, crf=12)
    summary = run_eval(spec, tmp_path)
    assert summary["frames"] >= 3
    assert summary["psnr"] >= 35.0, summary
    assert summary["pose_error_cm"]["max"] < 0.01


def test_same_seed_gives_identical_summary(tmp_path):
    spec = EvalSpec(method="quasar", latency_ms=50, jitter_ms=20, seed=7, **TINY)
    a = run_eval(spec, tmp_path / "a")
    b = run_eval(spec, tmp_path / "b")
    assert strip_wallclock(a) == strip_wallclock(b)
    # quasar's residual frames (reference every 5) are smaller than its references
    assert 0 < a["residual_to_reference_bytes"] < 1
    ja, jb = (json.loads((tmp_path / d / "summary.json").read_text()) for d in "ab")
    assert {k: v for k, v in ja.items() if k not in WALLCLOCK_KEYS} == \
        {k: v for k, v in jb.items() if k not in WALLCLOCK_KEYS}
    # A different seed changes the jitter, hence what arrives when.
    c = run_eval(EvalSpec(method="quasar", latency_ms=50, jitter_ms=20, seed=8, **TINY))
    assert strip_wallclock(c) != strip_wallclock(a)


def test_eval_outputs_and_fields(tmp_path):
    spec = EvalSpec(method="atw", latency_ms=20, jitter_ms=10, **TINY)
    s = run_eval(spec, tmp_path)
    for key in ("method", "scene", "trace", "latency_ms", "jitter_ms", "viewcell_m", "size", "frames", "mbps",
                "mbps_video", "mbps_geometry", "flip", "ssim", "psnr", "pose_error_cm", "pose_error_deg",
                "server_ms", "client_ms"):
        assert key in s, key
    assert s["mbps"] > 0 and s["mbps_geometry"] == 0
    assert 0 <= s["flip"] <= 1 and 0 <= s["ssim"] <= 1
    rows = list(csv.DictReader((tmp_path / "frames.csv").open()))
    assert len(rows) == s["frames"]
    html = (tmp_path / "report.html").read_text()
    assert html.count("data:image/png;base64") >= 3


def test_loss_makes_the_client_ask_for_references_and_recover():
    s = run_eval(EvalSpec(method="quasar", latency_ms=20, jitter_ms=5, loss=0.3, seed=3, **TINY))
    assert s["frames_lost"] > 0
    assert s["reference_requests"] > 0
    assert s["frames_applied"] > 0 and s["flip"] is not None


def test_loss_over_tcp_loses_no_frame_but_makes_them_late(tmp_path):
    # 5% loss of a TCP stream's segments: no frame is lost, but they come late (some after the run's end)
    kw = dict(method="quasar", latency_ms=20, jitter_ms=0, seed=3, tcp=True, **{**TINY, "frames": 60, "every": 6})
    lossy = run_eval(EvalSpec(loss=0.05, **kw), tmp_path / "lossy")
    run_eval(EvalSpec(**kw), tmp_path / "clean")
    assert lossy["tcp"] and lossy["frames_lost"] == 0 and lossy["reference_requests"] == 0
    assert lossy["frames_applied"] > 0

    def mean_age(run):
        return np.mean([float(r["age_ms"]) for r in csv.DictReader((tmp_path / run / "frames.csv").open())])
    assert mean_age("lossy") > mean_age("clean") + 20


def test_bad_eval_input_is_named():
    with pytest.raises(ValueError, match="unknown method"):
        run_eval(EvalSpec(method="teleport", **TINY))
    with pytest.raises(ValueError, match="lasts"):
        run_eval(EvalSpec(method="atw", **{**TINY, "frames": 100000}))
    for bad in (-1.0, float("nan"), 1e9):
        with pytest.raises(ValueError, match="--server-frame-ms"):
            run_eval(EvalSpec(method="atw", server_frame_ms=bad, **TINY))
    with pytest.raises(ValueError, match=r"chroma_qp_offset must be an integer in \[-12, 12\]; got 20"):
        run_eval(EvalSpec(method="atw", chroma_qp_offset=20, **TINY))


def test_sweep_writes_a_comparison_table(tmp_path):
    rows = run_sweep(EvalSpec(**TINY), tmp_path, methods=("atw", "meshwarp"), latencies=((20.0, 10.0),),
                     viewcells=(0.5,), quiet=True)
    assert [r["method"] for r in rows] == ["atw", "meshwarp"]
    table = (tmp_path / "table.md").read_text()
    assert "| atw" in table and "| meshwarp" in table
    assert (tmp_path / "quality_vs_rate.png").stat().st_size > 1000


def test_holes_and_black_frames_and_worst_strips_of_scored_frames_only(tmp_path):
    # 50 ms each way: the first frames are shown before any payload (black), and not scored.
    spec = EvalSpec(method="quasar", latency_ms=50, jitter_ms=0, **{**TINY, "every": 1, "frames": 14})
    s = run_eval(spec, tmp_path)
    assert s["frames_before_payload"] >= 5 and s["black_frames"] >= s["frames_before_payload"]
    assert 0 < s["residual_to_reference_bytes"] < 1
    assert s["frames"] == spec.frames - s["frames_before_payload"]
    assert set(s["holes"]) == {"mean", "std", "max"} and 0.0 <= s["holes"]["mean"] <= s["holes"]["max"] <= 1.0
    assert s["holes_empty"] + s["holes_smeared"] == pytest.approx(s["holes"]["mean"])
    assert 0 <= s["holes_interior"] <= s["holes"]["mean"]
    rows = list(csv.DictReader((tmp_path / "frames.csv").open()))
    assert all(int(r["frame_id"]) >= 0 and 0.0 <= float(r["holes"]) <= 1.0 for r in rows)
    html = (tmp_path / "report.html").read_text()
    assert "Holes over time" in html and "holes (magenta" in html
    first_scored = min(int(r["frame"]) for r in rows)
    captions = re.findall(r"<h3>frame (\d+) \(t=", html)
    assert len(captions) == 3 and all(int(c) >= first_scored for c in captions)


def test_atw_holes_are_its_smeared_edges():
    # builtin:orbit turns 36 deg/s: at 50 ms each way ATW shows some smeared edge pixels, never an empty one.
    s = run_eval(EvalSpec(method="atw", latency_ms=50, jitter_ms=0, **{**TINY, "trace": "builtin:orbit"}))
    assert s["holes"]["mean"] > 0 and s["holes_smeared"] == pytest.approx(s["holes"]["mean"]) and \
        s["holes_empty"] == 0


def test_eval_replays_a_trace_anchored_at_the_spawn_point(tmp_path):
    trace = tmp_path / "t.txt"
    resolve_trace("builtin:walk").window(0.0, 2.0).anchored([100.0, 5.0, 100.0], 0.0).save(trace)  # far away
    spec = EvalSpec(method="atw", **{**TINY, "trace": str(trace)}, anchor="spawn", start=0.5)
    s = run_eval(spec)
    assert s["anchor"] == "spawn" and s["start_s"] == 0.5
    far = run_eval(EvalSpec(method="atw", **{**TINY, "trace": str(trace)}, start=0.5))   # not anchored
    assert far["anchor"] is None and far["flip"] != s["flip"]
    with pytest.raises(TraceError, match="anchor"):
        run_eval(EvalSpec(method="atw", **TINY, anchor="1,2"))
    with pytest.raises(ValueError, match="after --start"):
        run_eval(EvalSpec(method="atw", **{**TINY, "trace": str(trace)}, start=1.9))


def test_adaptive_eval_over_a_rate_trace_records_each_frames_point(tmp_path):
    """--adapt with a Mahimahi trace: the summary has the frame age and its bound, and a timeline with each frame's
    operating point, which frames.csv repeats per scored frame; the report plots it; FLIP of the fovea too."""
    from quadcast.protocol.rate import load_ladder
    spec = EvalSpec(method="quasar", latency_ms=30, jitter_ms=10, rate_trace="builtin:step-100-15-100", adapt=True,
                    **{**TINY, "frames": 24})
    s = run_eval(spec, tmp_path)
    ladder = load_ladder()
    assert s["adapt"] is True and s["rate_trace"] == "builtin:step-100-15-100"
    assert s["age_bound_ms"] == pytest.approx(30 + 2000 / 30) and s["age_ms"] > 0
    tl = s["timeline"]
    assert tl["points"] == [p.name for p in ladder.points] + ["own"]      # above the ladder: the server's own settings
    assert len(tl["sent"]["point"]) == s["server_frames"] and all(0 <= i <= len(ladder) for i in tl["sent"]["point"])
    assert len(tl["display"]["age_ms"]) == 24 and tl["link"]["mbps"][0] == pytest.approx(100, rel=0.05)
    assert 0 < s["flip_fovea"] < 1
    rows = list(csv.DictReader((tmp_path / "frames.csv").open()))
    assert all(r["point"] != "" and r["flip_fovea"] != "" for r in rows)
    assert "Rate, operating point" in (tmp_path / "report.html").read_text()
    saved = json.loads((tmp_path / "summary.json").read_text())
    assert saved["timeline"]["sent"]["point"] == tl["sent"]["point"]


def test_fixed_operating_point_and_bad_rate_options(tmp_path):
    s = run_eval(EvalSpec(method="quasar", point="crf=35,hidden=0,fps=15", **TINY))
    assert s["point"]["crf"] == 35 and s["point"]["fps"] == 15
    assert s["server_frames"] <= 12 / 4 + 1          # 15 frames/s over 12 display frames at 60 Hz
    with pytest.raises(ValueError, match="operating points are quasar's knobs"):
        run_eval(EvalSpec(method="atw", adapt=True, **TINY))
    with pytest.raises(ValueError, match="give one of them"):
        run_eval(EvalSpec(method="quasar", rate_mbit=10, rate_trace="builtin:const-20", **TINY))
    with pytest.raises(ValueError, match="unknown; built-in rate traces"):
        run_eval(EvalSpec(method="quasar", rate_trace="builtin:nope", **TINY))
    with pytest.raises(ValueError, match="no point named"):
        run_eval(EvalSpec(method="quasar", point="no-such-point", **TINY))


def test_a_gaze_trace_moves_the_foveal_score(tmp_path):
    gaze = tmp_path / "gaze.txt"
    gaze.write_text("0 25 10\n")
    point = "sigma=4,fovea=5,max=32,atlas=4"
    centre = run_eval(EvalSpec(method="quasar", point=point, **TINY))
    off = run_eval(EvalSpec(method="quasar", point=point, gaze=str(gaze), **TINY))
    assert centre["flip_fovea"] != off["flip_fovea"] and centre["flip"] != off["flip"]
    gaze.write_text("0 100 0\n")
    with pytest.raises(ValueError, match="within"):
        run_eval(EvalSpec(method="quasar", point=point, gaze=str(gaze), **TINY))


def test_eval_start_fastest_picks_the_traces_fastest_motion_over_the_replay(tmp_path, capsys):
    """`quadcast eval --start fastest`: the start of the trace's fastest motion over the replay's --frames at 60 Hz
    (here a head still for 10 s but for a 90° turn from 6 to 7 s), printed; the whole trace where it is shorter."""
    from quadcast.cli import _eval_spec, build_parser
    t = np.arange(601) / 60.0
    yaw = np.interp(t, [0.0, 6.0, 7.0, 10.0], [0.0, 0.0, 90.0, 90.0])
    path = tmp_path / "turn.txt"
    path.write_text("".join(f"0 1.6 0 0 {y:.4f} 0 {1000 * s:.3f}\n" for s, y in zip(t, yaw)))
    parser = build_parser()
    spec = _eval_spec(parser.parse_args(["eval", "--trace", str(path), "--start", "fastest", "--frames", "60",
                                         "--out", str(tmp_path / "out")]))
    assert spec.start == pytest.approx(6.0, abs=1 / 60)
    assert "start at 6.00 s" in capsys.readouterr().out
    whole = parser.parse_args(["eval", "--trace", str(path), "--start", "fastest", "--frames", "900", "--out", "x"])
    assert _eval_spec(whole).start == 0.0
    assert parser.parse_args(["eval", "--start", "1.5", "--out", "x"]).start == 1.5
    with pytest.raises(SystemExit):
        parser.parse_args(["eval", "--start", "soon", "--out", "x"])
    assert "not seconds or 'fastest': 'soon'" in capsys.readouterr().err


def test_eval_queue_needs_tcp(tmp_path, capsys):
    from quadcast.cli import main
    assert main(["eval", "--scene", "builtin:courtyard", "--trace", "builtin:walk", "--method", "atw", "--queue", "64k",
                 "--out", str(tmp_path)]) == 2
    assert "--queue is the TCP downlink's queue" in capsys.readouterr().err


def test_a_trace_a_frame_too_short_says_how_many_frames_fit(tmp_path):
    """240 poses at 60 Hz last 3.983 s: the 240th display frame (at 4.000 s) is past the end, and the error says so
    to the millisecond, with the --frames that fits (it once read "lasts 4.0 s; 240 frames at 60 Hz need 4.0 s")."""
    t = np.arange(240) / 60.0
    rows = np.column_stack([np.zeros_like(t), np.full_like(t, 1.6), -0.5 * t, np.zeros((240, 3)), 1000.0 * t])
    trace = tmp_path / "short.txt"
    np.savetxt(trace, rows, fmt="%.5f")
    message = r"lasts 3\.983 s; 240 frames at 60 Hz need 4\.000 s \(--frames 239 fits\)"
    with pytest.raises(ValueError, match=message):
        run_eval(EvalSpec(method="atw", **{**TINY, "trace": str(trace), "frames": 240}))
