"""`quadcast demo`'s virtual-time twin: the same walk, size and link replayed in virtual time."""
from __future__ import annotations

import json
import os
import sys

import pytest

from quadcast.cli import build_parser
from quadcast.cli.demo import CLIENT_CORES, CLIENT_NICE, Child, client_cpus, virtual_twin


def test_the_demo_replays_its_walk_in_virtual_time(tmp_path):
    s = virtual_twin(tmp_path / "virtual", "160x90", 0.5, quiet=True)
    assert (s["method"], s["scene"], s["trace"], s["size"]) == ("quasar", "builtin:courtyard", "builtin:walk", "160x90")
    assert (s["latency_ms"], s["jitter_ms"], s["display_frames"]) == (20.0, 10.0, 30)
    assert s["frames"] >= 1 and 0.0 < s["flip"] < 1.0 and s["server_frames"] >= 1
    assert json.loads((tmp_path / "virtual" / "summary.json").read_text())["flip"] == pytest.approx(s["flip"], abs=1e-6)


def test_the_twin_replays_a_slow_server_at_its_frame_time(tmp_path):
    """With the live run's time per frame, the twin's server makes that many frames a second, not 30."""
    fast = virtual_twin(tmp_path / "fast", "160x90", 1.0, quiet=True)
    slow = virtual_twin(tmp_path / "slow", "160x90", 1.0, quiet=True, server_frame_ms=250.0)
    assert slow["server_frame_ms"] == 250.0 and fast["server_frame_ms"] == 0.0
    assert fast["server_frames"] >= 25
    assert 3 <= slow["server_frames"] <= 5          # one frame started at most every 250 ms over 1 s


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
    assert parser.parse_args(["demo"]).client_nice is None and CLIENT_NICE == 10
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
