"""Tests for sim.link: netem-like link model in virtual time and CLI parse helpers."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from quadcast.sim.link import (Delivery, LinkModel, RenoWindow, parse_bytes, parse_duration_ms, parse_loss,
                               parse_rate_mbit)


def test_delivery_time_is_delay_plus_serialization():
    link = LinkModel(delay_ms=20, rate_mbit=100)
    d = link.send(1.0, "frame", size_bytes=250_000)  # 2 Mbit at 100 Mbit/s = 20 ms
    assert isinstance(d, Delivery)
    assert d.t_sent == 1.0
    assert d.t_depart == pytest.approx(1.02)
    assert d.t_arrive == pytest.approx(1.04)
    assert d.latency == pytest.approx(0.04)


def test_no_rate_means_no_serialization_cost():
    link = LinkModel(delay_ms=5)
    d = link.send(0.5, "x", size_bytes=10**9)
    assert d.t_depart == 0.5
    assert d.t_arrive == pytest.approx(0.505)


@pytest.mark.parametrize("dist", ["uniform", "normal"])
def test_jitter_adds_to_delay_and_serialization(dist):
    link = LinkModel(delay_ms=30, jitter_ms=5, jitter=dist, rate_mbit=8, reorder=True, seed=3)
    jitters = []
    for i in range(2000):
        t = i * 0.01  # 10 ms apart, each message serializes in 1 ms: no queueing
        d = link.send(t, i, size_bytes=1000)
        assert d.t_depart == pytest.approx(t + 0.001)
        jitters.append(d.t_arrive - d.t_depart - 0.030)
    jitters = np.array(jitters)
    assert abs(jitters.mean()) < 0.0005
    if dist == "uniform":
        assert jitters.min() >= -0.005 - 1e-12 and jitters.max() <= 0.005 + 1e-12
        assert jitters.min() < -0.0045 and jitters.max() > 0.0045
        assert jitters.std() == pytest.approx(0.005 / np.sqrt(3), rel=0.1)
    else:
        assert jitters.std() == pytest.approx(0.005, rel=0.1)


def test_normal_jitter_never_arrives_before_departure():
    link = LinkModel(delay_ms=1, jitter_ms=10, jitter="normal", reorder=True, seed=0)
    ds = [link.send(i * 0.001, i, 100) for i in range(500)]
    assert all(d.t_arrive >= d.t_depart for d in ds)
    assert sum(d.t_arrive == d.t_depart for d in ds) > 100  # clipping happened


def test_queueing_behind_a_big_message():
    link = LinkModel(delay_ms=10, rate_mbit=8)  # 1 byte per microsecond
    big = link.send(0.0, "big", size_bytes=1_000_000)  # occupies the link for 1 s
    small = link.send(0.1, "small", size_bytes=1000)
    assert big.t_depart == pytest.approx(1.0)
    assert small.t_depart == pytest.approx(1.001)
    assert small.t_arrive == pytest.approx(1.011)
    assert link.link_free_at == pytest.approx(1.001)
    # After the queue drains, a new message is not delayed.
    later = link.send(5.0, "later", size_bytes=1000)
    assert later.t_depart == pytest.approx(5.001)


def test_in_order_without_reorder_even_with_large_jitter():
    link = LinkModel(delay_ms=50, jitter_ms=40, seed=1)
    sent = [link.send(i * 0.002, i, 500) for i in range(300)]
    arrivals = [d.t_arrive for d in sent]
    assert arrivals == sorted(arrivals)
    got = link.poll(10.0)
    assert [d.message for d in got] == list(range(300))


def test_reorder_allows_overtaking_with_large_jitter():
    link = LinkModel(delay_ms=50, jitter_ms=40, reorder=True, seed=1)
    for i in range(300):
        link.send(i * 0.002, i, 500)
    got = link.poll(10.0)
    order = [d.message for d in got]
    assert sorted(order) == list(range(300))
    inversions = sum(a > b for a, b in zip(order, order[1:]))
    assert inversions > 30
    assert [d.t_arrive for d in got] == sorted(d.t_arrive for d in got)


def test_poll_next_arrival_and_pending():
    link = LinkModel(delay_ms=10)
    assert link.next_arrival() is None and link.pending() == 0 and link.poll(1e9) == []
    link.send(0.0, "a", 10)
    link.send(0.005, "b", 20)
    assert link.pending() == 2
    assert link.next_arrival() == pytest.approx(0.010)
    assert link.poll(0.0099) == []
    assert [d.message for d in link.poll(0.010)] == ["a"]
    assert link.next_arrival() == pytest.approx(0.015)
    assert [d.message for d in link.poll(1.0)] == ["b"]
    assert link.pending() == 0 and link.next_arrival() is None
    assert link.stats.delivered == 2 and link.stats.bytes_delivered == 30


def dropped_set(seed, loss, n, **kw):
    link = LinkModel(loss=loss, seed=seed, **kw)
    return {i for i in range(n) if link.send(i * 1e-3, i, 100) is None}, link


def test_loss_is_seeded_and_near_the_requested_fraction():
    n, loss = 20_000, 0.1
    a, link = dropped_set(42, loss, n)
    b, _ = dropped_set(42, loss, n, delay_ms=20, jitter_ms=5)  # jitter settings do not change losses
    c, _ = dropped_set(43, loss, n)
    assert a == b
    assert a != c
    assert abs(len(a) / n - loss) < 0.01  # binomial std is 0.002
    assert link.stats.sent == n and link.stats.dropped == len(a)
    assert link.stats.bytes_sent == 100 * n and link.stats.bytes_dropped == 100 * len(a)
    assert link.pending() == n - len(a)


def test_same_seed_reproduces_identical_deliveries():
    def run(seed):
        link = LinkModel(delay_ms=20, jitter_ms=8, jitter="normal", rate_mbit=50, loss=0.05, reorder=True, seed=seed)
        for i in range(200):
            link.send(i * 0.003, i, 1200 + 37 * i)
        return link.poll(1e9)

    assert run(5) == run(5)
    assert run(5) != run(6)


def test_zero_loss_never_drops():
    dropped, _ = dropped_set(0, 0.0, 1000)
    assert dropped == set()


@settings(max_examples=40, deadline=None)
@given(
    steps=st.lists(
        st.tuples(st.floats(0.0, 0.05), st.integers(0, 200_000)), min_size=1, max_size=40
    ),
    delay=st.floats(0, 100),
    jitter=st.floats(0, 100),
    rate=st.one_of(st.none(), st.floats(0.1, 1000)),
    seed=st.integers(0, 2**32 - 1),
)
def test_link_invariants(steps, delay, jitter, rate, seed):
    link = LinkModel(delay_ms=delay, jitter_ms=jitter, rate_mbit=rate, seed=seed)
    t, prev = 0.0, None
    for gap, size in steps:
        t += gap
        d = link.send(t, None, size)
        assert d.t_sent <= d.t_depart <= d.t_arrive
        if rate is not None:
            assert d.t_depart >= t + size * 8 / (rate * 1e6) - 1e-12
        if prev is not None:
            assert d.t_arrive >= prev.t_arrive  # no reorder by default
            if rate is not None:
                assert d.t_depart >= prev.t_depart
        prev = d
    delivered = link.poll(np.inf)
    assert [d.seq for d in delivered] == list(range(len(steps)))


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"delay_ms": -1}, "delay_ms"),
        ({"jitter_ms": -0.5}, "jitter_ms"),
        ({"jitter": "pareto"}, "jitter"),
        ({"rate_mbit": 0}, "rate_mbit"),
        ({"loss": 1.0}, "loss"),
        ({"loss": -0.1}, "loss"),
        ({"delay_ms": float("nan")}, "delay_ms"),
    ],
)
def test_invalid_parameters_raise(kwargs, match):
    with pytest.raises(ValueError, match=match):
        LinkModel(**kwargs)


def test_invalid_send_raises():
    link = LinkModel()
    with pytest.raises(ValueError, match="size_bytes"):
        link.send(0.0, "x", -1)
    with pytest.raises(ValueError, match="size_bytes"):
        link.send(0.0, "x", 1.5)
    with pytest.raises(ValueError, match="finite"):
        link.send(float("nan"), "x", 1)


# -- parse helpers ----------------------------------------------------------------


@pytest.mark.parametrize(
    "text, ms",
    [("20ms", 20.0), ("0.02s", 20.0), ("20", 20.0), (" 1.5 ms ", 1.5), ("500us", 0.5), ("2s", 2000.0), ("0", 0.0), (7, 7.0)],
)
def test_parse_duration_ms(text, ms):
    assert parse_duration_ms(text) == pytest.approx(ms)


@pytest.mark.parametrize(
    "text, mbit",
    [("200mbit", 200.0), ("1gbit", 1000.0), ("500kbit", 0.5), ("1Gbit", 1000.0), ("9600bit", 0.0096), ("100", 100.0), ("1mbps", 8.0)],
)
def test_parse_rate_mbit(text, mbit):
    assert parse_rate_mbit(text) == pytest.approx(mbit)


@pytest.mark.parametrize("text, frac", [("0.5%", 0.005), ("0.005", 0.005), ("0", 0.0), ("10 %", 0.1), (0.2, 0.2)])
def test_parse_loss(text, frac):
    assert parse_loss(text) == pytest.approx(frac)


@pytest.mark.parametrize("text, n", [("64k", 65536), ("128KB", 131072), ("16m", 16 << 20), ("1g", 1 << 30),
                                     ("1500", 1500), (" 2 k ", 2048), (4096, 4096)])
def test_parse_bytes(text, n):
    assert parse_bytes(text) == n


def test_parse_bytes_takes_a_minimum():
    """A limit may be 0 (`quadcast server --unsent 0`); a queue needs a byte at least (the default)."""
    assert parse_bytes("0", minimum=0) == 0 and parse_bytes("0k", minimum=0) == 0
    with pytest.raises(ValueError, match="at least 1 byte"):
        parse_bytes("0")
    with pytest.raises(ValueError, match="at least 0 bytes"):
        parse_bytes("-1k", minimum=0)


@pytest.mark.parametrize(
    "func, text",
    [
        (parse_bytes, "lots"),
        (parse_bytes, "0"),
        (parse_bytes, "-1k"),
        (parse_bytes, "5 parsecs"),
        (parse_duration_ms, "20 parsecs"),
        (parse_duration_ms, "-5ms"),
        (parse_duration_ms, ""),
        (parse_rate_mbit, "fast"),
        (parse_rate_mbit, "10 furlongs"),
        (parse_rate_mbit, "0mbit"),
        (parse_loss, "lots"),
        (parse_loss, "100%"),
        (parse_loss, "5"),
    ],
)
def test_parse_helpers_reject_bad_text_naming_it(func, text):
    with pytest.raises(ValueError) as err:
        func(text)
    assert repr(text) in str(err.value)


def test_parse_loss_suggests_percent_for_bare_numbers_above_one():
    with pytest.raises(ValueError, match="did you mean '5%'"):
        parse_loss("5")


# -- a reliable (TCP) link ---------------------------------------------------------------------------------------------

def test_tcp_link_sends_a_window_per_round_trip_in_slow_start():
    link = LinkModel(delay_ms=20, reliable=True, mss_bytes=1000, initial_window=10)
    # 45 segments: 10, then 20, then the last 15 of a window of 40 -- two round trips (80 ms) before the last leaves
    d = link.send(0.0, "a", 45_000)
    assert d.t_depart == pytest.approx(0.080) and d.t_arrive == pytest.approx(0.100)
    assert link.window.cwnd == 40 and link.stats.segments_sent == 45
    # the next message, once the last round's acknowledgements are back, finds the window it left (not full: no
    # growth) and fits in one round
    d = link.send(1.0, "b", 30_000)
    assert d.t_depart == pytest.approx(1.0) and link.window.cwnd == 40


def test_tcp_link_delays_a_message_by_a_round_trip_each_time_its_segment_is_lost():
    link = LinkModel(delay_ms=10, reliable=True, loss=0.1, seed=2, mss_bytes=1000)
    delayed = 0
    for i in range(100):   # 0.5 s apart: the link is idle, and the window (2 segments at least) never limits them
        lost_before = link.stats.segments_lost
        d = link.send(0.5 * i, i, 1_000)
        extra = (d.latency - 0.010) / 0.020
        if link.stats.segments_lost > lost_before:
            delayed += 1
            assert extra >= 1 - 1e-9 and extra == pytest.approx(round(extra))
        else:
            assert extra == pytest.approx(0.0)
    assert delayed >= 5


def test_tcp_link_never_drops_and_sends_lost_segments_again_a_round_trip_later():
    def arrivals(loss, seed):
        link = LinkModel(delay_ms=10, reliable=True, loss=loss, seed=seed, mss_bytes=1000)
        return link, [link.send(0.05 * i, i, 5_000) for i in range(200)]
    clean, base = arrivals(0.0, 1)
    lossy, got = arrivals(0.05, 1)
    assert all(d is not None for d in got) and [d.message for d in got] == list(range(200))
    assert lossy.stats.dropped == 0 and lossy.stats.segments_lost > 0
    assert clean.stats.segments_lost == 0 and all(d.latency == pytest.approx(0.010) for d in base)
    late = [d.latency for d in got if d.latency > 0.0101]
    # a loss costs its message at least one round trip (20 ms), and a later message waits for an earlier one
    assert late and min(late) >= 0.030 - 1e-9
    assert all(b.t_arrive >= a.t_arrive for a, b in zip(got, got[1:]))


def test_tcp_window_halves_after_a_lossy_round_and_grows_a_segment_a_round_after():
    w = RenoWindow(cwnd=20.0)
    w.next_round(0.0)
    w.used, w.lost = 20, 1
    w.next_round(0.1)
    assert (w.cwnd, w.ssthresh) == (10.0, 10.0)
    w.used = 10
    w.next_round(0.2)
    assert w.cwnd == pytest.approx(11.0)           # congestion avoidance: one segment a full round
    w.used = 3
    w.next_round(0.3)
    assert w.cwnd == pytest.approx(11.0)           # a round that did not use the window does not grow it


@pytest.mark.parametrize("loss", [0.005, 0.02])
def test_tcp_link_rate_under_random_loss_follows_the_square_root_law(loss):
    # Mathis et al. (1997): a Reno stream's rate is about MSS / RTT * sqrt(3 / (2 p)) under random loss p
    link = LinkModel(delay_ms=20, reliable=True, loss=loss, seed=5)
    size = 40_000_000   # long enough that slow start's first rounds do not count
    d = link.send(0.0, "bulk", size)
    rate = size / d.t_depart
    predicted = 1448 / 0.040 * (1.5 / loss) ** 0.5
    assert 0.6 * predicted < rate < 1.5 * predicted
    assert link.stats.segments_lost == pytest.approx(link.stats.segments_sent * loss, rel=0.3)


def test_tcp_link_still_serializes_at_the_rate():
    link = LinkModel(delay_ms=5, rate_mbit=8, reliable=True, initial_window=1000)
    d = link.send(0.0, "x", 100_000)
    assert d.t_depart == pytest.approx(0.1, rel=0.02)


@pytest.mark.parametrize("kw, word", [({"reorder": True}, "reorder"), ({"mss_bytes": 0}, "mss_bytes"),
                                      ({"initial_window": 0.5}, "initial_window"), ({"rtt_ms": -1}, "rtt_ms"),
                                      ({"loss": 0.6}, "at most 50%")])
def test_tcp_link_rejects_bad_parameters(kw, word):
    with pytest.raises(ValueError, match=word):
        LinkModel(reliable=True, **kw)


@settings(max_examples=150, deadline=None)
@given(sends=st.lists(st.tuples(st.floats(0.0, 0.2), st.integers(0, 200_000)), min_size=1, max_size=30),
       delay=st.floats(0.0, 50.0), jitter=st.floats(0.0, 20.0), rate=st.none() | st.floats(0.5, 500.0),
       loss=st.floats(0.0, 0.5), seed=st.integers(0, 2**16))
def test_tcp_link_delivers_every_message_once_in_order_no_sooner_than_the_wire_allows(sends, delay, jitter, rate,
                                                                                    loss, seed):
    link = LinkModel(delay_ms=delay, jitter_ms=jitter, rate_mbit=rate, loss=loss, seed=seed, reliable=True)
    t, got = 0.0, []
    for i, (dt, size) in enumerate(sends):
        t += dt
        d = link.send(t, i, size)
        assert d is not None and d.t_depart >= t + link.serialization_time(size) * (1 - 1e-9) - 1e-12
        assert d.t_arrive >= d.t_depart
        got.append(d)
    assert [d.message for d in link.poll(math.inf)] == list(range(len(sends)))
    assert all(b.t_arrive >= a.t_arrive for a, b in zip(got, got[1:]))
    segments = sum(max(1, -(-size // link.mss_bytes)) for _, size in sends)
    assert link.stats.segments_sent == segments + link.stats.segments_lost
    assert link.stats.dropped == 0 and link.window.cwnd >= 2.0


def test_tcp_link_counts_its_unsent_bytes_and_forgets_what_left():
    link = LinkModel(delay_ms=10, rate_mbit=8, reliable=True, initial_window=1000)   # 1 MB/s
    for i in range(10):
        link.send(0.0, i, 10_000)                 # each leaves 10 ms after the one before
    assert link.unsent_bytes(0.0) == 100_000 and link.unsent_bytes(0.05) == 50_000
    assert link.unsent_at_most(20_000, 0.05) == pytest.approx(0.08)
    assert link.unsent_at_most(20_000, 0.2) == 0.2 and link.unsent_bytes(0.2) == 0
    for i in range(1, 2_000):                     # a long run keeps only what has not left
        link.send(0.2 + i * 0.01, i, 1_000)
    assert len(link._unsent) <= 2
