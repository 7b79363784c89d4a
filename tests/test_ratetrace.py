"""Mahimahi bandwidth traces (quadcast.sim.ratetrace) and the link model driven by one."""
from __future__ import annotations

import numpy as np
import pytest

from quadcast.sim.link import LinkModel
from quadcast.sim.ratetrace import (PACKET_BYTES, SHIPPED_TRACES, RateTrace, RateTraceError, resolve_rate_trace,
                                    trace_from_schedule)


def test_parse_and_errors_name_the_line():
    t = RateTrace.parse("# a comment\n1\n1\n\n3\n", "t")
    assert t.opportunities_ms.tolist() == [1, 1, 3] and t.period_ms == 3
    assert t.mean_mbit == pytest.approx(3 * PACKET_BYTES * 8 / 3e3)
    with pytest.raises(RateTraceError, match="t line 2: expected an integer"):
        RateTrace.parse("1\nx\n", "t")
    with pytest.raises(RateTraceError, match="line 3: 1 ms is earlier"):
        RateTrace.parse("1\n2\n1\n", "t")
    with pytest.raises(RateTraceError, match="no delivery opportunities"):
        RateTrace.parse("# nothing\n", "t")
    with pytest.raises(RateTraceError, match="period and must be > 0"):
        RateTrace.parse("0\n0\n", "t")
    with pytest.raises(RateTraceError, match="must be >= 0"):
        RateTrace.parse("-1\n5\n", "t")


def test_a_one_line_trace_is_12_mbit_and_repeats():
    t = RateTrace.parse("1\n", "12mbit")
    assert t.mean_mbit == pytest.approx(12.0)
    # 3000 bytes from t = 0: two opportunities, at 1 ms and 2 ms
    depart, cursor = t.depart(0.0, 3000, None)
    assert depart == pytest.approx(0.002) and cursor == (2, 0)
    # the stream goes on where it stopped: 500 bytes use the opportunity at 3 ms, 1500 more finish at 4 ms
    depart, cursor = t.depart(0.0, 500, cursor)
    assert depart == pytest.approx(0.003) and cursor == (2, 500)
    depart, cursor = t.depart(0.0, 1500, cursor)
    assert depart == pytest.approx(0.004) and cursor == (3, 500)
    # an idle link loses its opportunities: offered at 1 s, the first one used is at 1 s itself
    depart, cursor = t.depart(1.0, 1500, cursor)
    assert depart == pytest.approx(1.0)


def test_schedule_traces_have_their_rates():
    t = trace_from_schedule([(1.0, 100.0), (1.5, 15.0), (1.5, 100.0)], "step")
    centres, mbps = t.rate_mbit(0.0, 4.0, 0.25)
    assert np.allclose(mbps[centres < 1.0], 100.0, rtol=0.02)
    assert np.allclose(mbps[(centres > 1.0) & (centres < 2.5)], 15.0, rtol=0.05)
    assert np.allclose(mbps[centres > 2.5], 100.0, rtol=0.02)
    # it repeats: the next period starts at 100 Mbit/s again
    _, again = t.rate_mbit(4.0, 4.5, 0.25)
    assert np.allclose(again, 100.0, rtol=0.02)
    with pytest.raises(RateTraceError, match="seconds > 0 and Mbit/s > 0"):
        trace_from_schedule([(1.0, 0.0)])


@pytest.mark.parametrize("name", sorted(SHIPPED_TRACES))
def test_shipped_traces_are_what_their_generator_makes(name):
    shipped = resolve_rate_trace(f"builtin:{name}")
    made = trace_from_schedule(SHIPPED_TRACES[name], name)
    assert np.array_equal(shipped.opportunities_ms, made.opportunities_ms) and shipped.period_ms == made.period_ms
    with pytest.raises(RateTraceError, match="unknown; built-in rate traces are"):
        resolve_rate_trace("builtin:nope")


def test_link_model_follows_the_trace(tmp_path):
    path = tmp_path / "step.mahi"
    path.write_text(trace_from_schedule([(1.0, 80.0), (1.0, 8.0)], "step").to_text())
    link = LinkModel(delay_ms=10, rate_trace=RateTrace.load(path))
    fast = link.send(0.1, "a", 100_000)           # 10 ms at 80 Mbit/s
    slow = link.send(1.1, "b", 100_000)           # 100 ms at 8 Mbit/s
    assert fast.t_depart - 0.1 == pytest.approx(0.010, abs=0.0015)
    assert slow.t_depart - 1.1 == pytest.approx(0.100, abs=0.0015)
    assert slow.t_arrive == pytest.approx(slow.t_depart + 0.010)
    # messages queue behind each other as with a fixed rate
    q1, q2 = link.send(1.5, "c", 50_000), link.send(1.5, "d", 50_000)
    assert q2.t_depart - q1.t_depart == pytest.approx(0.050, abs=0.0015)
    # trace_start shifts the trace: the same message at link time 1.1 with the trace started at 1.0 is fast
    shifted = LinkModel(rate_trace=RateTrace.load(path), trace_start=1.0)
    assert shifted.send(1.1, "e", 100_000).t_depart - 1.1 == pytest.approx(0.010, abs=0.0015)
    with pytest.raises(ValueError, match="not both"):
        LinkModel(rate_mbit=10, rate_trace=RateTrace.load(path))
    with pytest.raises(RateTraceError, match="missing.mahi"):
        RateTrace.load(tmp_path / "missing.mahi")
