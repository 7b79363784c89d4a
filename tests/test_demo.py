"""`quadcast demo`'s virtual-time twin: the same walk, size and link replayed in virtual time."""
from __future__ import annotations

import json

import pytest

from quadcast.cli.demo import virtual_twin


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
