"""`quadcast demo`: what it follows (`DemoView`), its virtual-time twin (the same trace, size and link replayed in
virtual time) and how it starts its processes."""
from __future__ import annotations

import json
import os
import sys

import pytest

from quadcast.cli import build_parser
from quadcast.cli.demo import (CLIENT_CORES, CLIENT_NICE, DEMO_SECONDS, Child, DemoView, client_cpus, run_demo,
                               virtual_twin)
from quadcast.render.traces import TraceError, resolve_trace


def test_the_demo_replays_its_walk_in_virtual_time(tmp_path):
    s = virtual_twin(tmp_path / "virtual", DemoView(size="160x90", duration=0.5), quiet=True)
    assert (s["method"], s["scene"], s["trace"], s["size"]) == ("quasar", "builtin:courtyard", "builtin:walk", "160x90")
    assert (s["latency_ms"], s["jitter_ms"], s["display_frames"]) == (20.0, 10.0, 30)
    assert s["frames"] >= 1 and 0.0 < s["flip"] < 1.0 and s["server_frames"] >= 1
    assert json.loads((tmp_path / "virtual" / "summary.json").read_text())["flip"] == pytest.approx(s["flip"], abs=1e-6)


def test_the_twin_replays_a_slow_server_at_its_frame_time(tmp_path):
    """With the live run's time per frame, the twin's server makes that many frames a second, not 30."""
    view = DemoView(size="160x90", duration=1.0)
    fast = virtual_twin(tmp_path / "fast", view, quiet=True)
    slow = virtual_twin(tmp_path / "slow", view, quiet=True, server_frame_ms=250.0)
    assert slow["server_frame_ms"] == 250.0 and fast["server_frame_ms"] == 0.0
    assert fast["server_frames"] >= 25
    assert 3 <= slow["server_frames"] <= 5          # one frame started at most every 250 ms over 1 s


def test_the_demo_follows_another_trace_in_another_scene(tmp_path):
    """A trace file re-anchored at the scene's spawn point, from its fastest window: the twin replays that window
    there, and the client is told the same (its options are `quadcast eval`'s)."""
    trace = tmp_path / "far.txt"
    resolve_trace("builtin:orbit").window(0.0, 3.0).anchored([100.0, 5.0, 100.0], 0.0).save(trace)
    view = DemoView(scene="builtin:courtyard-static", trace=str(trace), anchor="spawn", start="fastest",
                    duration=0.5, size="160x90").resolved()
    assert view.start == resolve_trace(str(trace)).fastest_window(0.5) and view.duration == 0.5
    args = view.trace_args()
    assert args[:6] == ["--scene", "builtin:courtyard-static", "--trace", str(trace), "--anchor", "spawn"]
    assert args[6:] == ([] if view.start == 0 else ["--start", str(view.start)])
    assert build_parser().parse_args(["eval", *args, "--out", "x"]).anchor == "spawn"
    s = virtual_twin(tmp_path / "virtual", view, quiet=True)
    assert (s["scene"], s["trace"], s["anchor"], s["display_frames"]) == ("builtin:courtyard-static", str(trace),
                                                                          "spawn", 30)
    assert s["start_s"] == view.start and s["frames"] >= 1 and 0.0 < s["flip"] < 1.0


def test_the_live_demo_runs_on_the_scene_and_trace_it_is_given(tmp_path, capsys):
    """Server, link and client as processes, the server rendering the scene given and the client following the
    trace given from its fastest second (no virtual-time replay: the tests above cover it)."""
    trace = tmp_path / "orbit.txt"
    resolve_trace("builtin:orbit").window(0.0, 3.0).save(trace)
    view = DemoView(scene="builtin:courtyard-static", trace=str(trace), anchor="spawn", start="fastest",
                    duration=1.0, size="160x90")
    assert run_demo(tmp_path / "demo", quiet=False, view=view, compare=False) == 0     # children's lines echoed
    s = json.loads((tmp_path / "demo" / "client" / "summary.json").read_text())
    assert (s["scene"], s["trace"], s["size"]) == ("builtin:courtyard-static", str(trace), "160x90")
    assert s["start_s"] == pytest.approx(view.resolved().start) and s["server_frames"] >= 1 and s["frames"] >= 1
    out = capsys.readouterr().out
    assert "scene builtin:courtyard-static" in out                     # the server's ready line
    assert "warmed up: quasar" in (tmp_path / "demo" / "server.log").read_text()   # its spare workers warmed up
    assert f"on {trace} in builtin:courtyard-static at 160x90" in out


def test_the_live_demo_runs_over_webrtc(tmp_path, capsys):
    """The same three processes speaking WebRTC: the link answers the client's offer and shapes the datagrams."""
    view = DemoView(scene="builtin:courtyard-static", duration=1.0, size="160x90")
    assert run_demo(tmp_path / "demo", quiet=True, view=view, compare=False, transport="webrtc") == 0
    s = json.loads((tmp_path / "demo" / "client" / "summary.json").read_text())
    assert s["transport"] == "webrtc" and s["server_frames"] >= 1 and s["frames"] >= 1
    assert "over webrtc" in capsys.readouterr().out
    assert "rtc-link" in (tmp_path / "demo" / "link.log").read_text()     # the WebRTC link, not the TCP proxy
    with pytest.raises(ValueError, match="transport must be one of tcp, webrtc"):
        run_demo(tmp_path / "demo2", view=view, compare=False, transport="quic")


def test_what_the_demo_follows_is_checked_before_it_starts(tmp_path):
    walk = resolve_trace("builtin:walk")
    default = DemoView().resolved()
    assert (default.scene, default.trace, default.start, default.duration) == ("builtin:courtyard", "builtin:walk",
                                                                               0.0, DEMO_SECONDS)
    short = tmp_path / "short.txt"
    walk.window(0.0, 4.0).save(short)
    rest = resolve_trace(str(short)).duration
    assert DemoView(trace=str(short)).resolved().duration == rest      # 10 s unless the trace ends sooner
    assert DemoView(trace=str(short), start=1.0).resolved().duration == pytest.approx(rest - 1.0)
    assert DemoView(trace=str(short), start="fastest").resolved().start == 0.0    # its whole length
    for view, why in ((DemoView(trace=str(short), duration=5.0), "has 4.00 s left after --start 0 s, less than "
                                                                 "--duration 5 s"),
                      (DemoView(start=walk.duration + 1), "--start must be 'fastest' or seconds in"),
                      (DemoView(start=-1.0), "--start must be"),
                      (DemoView(duration=0.0), "--duration must be > 0 s"),
                      (DemoView(size="big"), "size must look like 960x540"),
                      (DemoView(anchor="north"), "anchor 'north': expected 'spawn' or"),
                      (DemoView(trace=str(tmp_path / "none.txt")), "not found"),
                      (DemoView(trace=str(short), start="fastest", duration=6.0), "shorter than a 6 s window")):
        with pytest.raises((ValueError, TraceError), match=why):
            view.resolved()


def test_demo_trace_options(capsys):
    parser = build_parser()
    args = parser.parse_args(["demo"])
    assert (args.scene, args.trace, args.anchor, args.start, args.duration, args.size) == (
        "builtin:courtyard", "builtin:walk", None, 0.0, None, "480x270")
    args = parser.parse_args(["demo", "--scene", "monastery", "--trace", "t.txt", "--anchor", "spawn", "--start",
                              "fastest", "--duration", "4", "--size", "320x180"])
    assert (args.scene, args.trace, args.anchor, args.start, args.duration, args.size) == (
        "monastery", "t.txt", "spawn", "fastest", 4.0, "320x180")
    assert parser.parse_args(["demo", "--start", "2.5"]).start == 2.5
    with pytest.raises(SystemExit):
        parser.parse_args(["demo", "--start", "soon"])
    assert "not seconds or 'fastest': 'soon'" in capsys.readouterr().err


def _niceness_of(child: Child) -> int:
    line = child.wait_for(r"^-?\d+$", 30).group(0)
    child.wait(30)
    return int(line)


def test_a_child_can_run_below_this_process_priority(tmp_path):
    """The demo's client runs `nice` below the server and link: the child's niceness is ours plus the increment."""
    ours = os.nice(0)
    argv = [sys.executable, "-c", "import os; print(os.nice(0))"]
    assert _niceness_of(Child("same", argv, tmp_path / "same.log")) == ours
    assert _niceness_of(Child("niced", argv, tmp_path / "niced.log", nice=5)) == min(19, ours + 5)
    with pytest.raises(ValueError, match="nice must be 0..19, got 20"):
        Child("bad", argv, nice=20)


def test_demo_client_nice_option(capsys):
    parser = build_parser()
    assert parser.parse_args(["demo"]).client_nice is None and CLIENT_NICE == 19
    assert parser.parse_args(["demo", "--client-nice", "0"]).client_nice == 0
    for bad, why in (("20", "must be 0..19"), ("x", "not an integer")):
        with pytest.raises(SystemExit):
            parser.parse_args(["demo", "--client-nice", bad])
        assert why in capsys.readouterr().err


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="CPU affinity is Linux's")
def test_a_child_can_run_on_some_cpus_only(tmp_path):
    """The demo's client runs on the last of the machine's cores (`client_cpus`): the child's affinity is that set,
    its threads' too; a set that is empty or holds CPUs this process may not use is refused."""
    ours = sorted(os.sched_getaffinity(0))
    argv = [sys.executable, "-c", "import os, threading; t = threading.Thread(target=lambda: "
            "print(sorted(os.sched_getaffinity(0)), flush=True)); t.start(); t.join(); "
            "print(sorted(os.sched_getaffinity(0)))"]
    child = Child("placed", argv, tmp_path / "placed.log", nice=3, cpus={ours[-1]})
    child.wait(30)
    assert child.lines == [f"[{ours[-1]}]"] * 2
    for bad in (set(), {max(ours) + 1}):
        with pytest.raises(ValueError, match="cpus must be a non-empty subset"):
            Child("bad", argv, cpus=bad)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="CPU affinity is Linux's")
def test_the_demo_client_gets_the_last_cores():
    ours = sorted(os.sched_getaffinity(0))
    assert CLIENT_CORES == 1
    assert client_cpus(0) is None and client_cpus(len(ours)) is None and client_cpus(len(ours) + 3) is None
    if len(ours) >= 2:
        assert client_cpus(1) == {ours[-1]} and client_cpus(len(ours) - 1) == set(ours[1:])
    with pytest.raises(ValueError, match="client cores must be >= 0, got -1"):
        client_cpus(-1)


def test_demo_client_cores_option(capsys):
    parser = build_parser()
    assert parser.parse_args(["demo"]).client_cores is None
    assert parser.parse_args(["demo", "--client-cores", "0"]).client_cores == 0
    for bad, why in (("-1", "must be >= 0"), ("one", "not an integer")):
        with pytest.raises(SystemExit):
            parser.parse_args(["demo", "--client-cores", bad])
        assert why in capsys.readouterr().err


def test_a_child_is_waited_for_in_its_log(tmp_path):
    """`Child.wait_for_log` finds what the process writes to its log (stderr) after the call, and says which pattern
    never came."""
    code = "import sys, time; time.sleep(0.3); print('session 7 ended: 12 poses', file=sys.stderr, flush=True)"
    child = Child("logger", [sys.executable, "-c", code], tmp_path / "logger.log")
    try:
        assert child.wait_for_log(r"session (\d+) ended", 30).group(1) == "7"
        with pytest.raises(RuntimeError, match="logger's log has no 'never'"):
            child.wait_for_log("never", 0.5)
    finally:
        child.wait(30)
