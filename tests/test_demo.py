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
