"""Rate adaptation (quadcast.protocol.rate): operating points, the ladder, and the controller in the session core,
driven through the virtual-time replay with GL-free stand-ins for the method's two halves (frame sizes follow the
operating point, tests/stubs.py), over fixed-rate and Mahimahi-trace links."""
from __future__ import annotations

import json

import numpy as np
import pytest

from dataclasses import replace

from quadcast.protocol.rate import (OWN_POINT, Ladder, LadderError, OperatingPoint, RateConfig, RateController,
                                    fovea_scale, ladder_points, load_ladder, own_point, pareto_front,
                                    session_rate)
from quadcast.protocol.session import SendReport, ServerSession, ServerSessionConfig, ClientSession
from quadcast.render.traces import resolve_trace
from quadcast.sim.ratetrace import trace_from_schedule
from quadcast.sim.replay import ReplayConfig, replay
from stubs import StubClient, StubServer

LADDER = Ladder(tuple(OperatingPoint(f"p{i}", crf=23 + i, mbps=m, flip=0.2 - 0.02 * i)
                      for i, m in enumerate((2.0, 4.0, 8.0, 12.0, 16.0, 24.0, 32.0, 64.0))), command="test ladder")
LATENCY_MS = 50.0
BOUND_MS = LATENCY_MS + 2 * 1000 / 30          # the acceptance bound on frame age: latency + two frame intervals


# ----------------------------------------------------------------------------------------- points, ladder

def test_operating_points_check_and_parse():
    p = OperatingPoint.parse("crf=30,quad=4,hidden=1,fps=15,sigma=8,atlas=4")
    assert (p.crf, p.quad_scale, p.hidden_layers, p.fps, p.fovea_sigma_deg, p.fovea_atlas) == (30, 4, 1, 15, 8, 4)
    assert p.foveated and not OperatingPoint().foveated
    assert p.knobs() == OperatingPoint.from_dict(p.to_dict()).knobs()
    for spec, match in (("crf=99", "crf must be in"), ("hidden=-1", "hidden_layers must be >= 0"),
                        ("quad=0", "quad_scale must be > 0"), ("fps=0", "fps must be in"), ("bogus=1", "key=value"),
                        ("crf=x", "crf needs a number"), ("atlas=16", "fovea_atlas must be in")):
        with pytest.raises(LadderError, match=match):
            OperatingPoint.parse(spec)
    with pytest.raises(LadderError, match="unknown field"):
        OperatingPoint.from_dict({"name": "x", "speed": 3})


def test_fovea_scale_is_one_in_the_fovea_and_grows_to_its_cap():
    e = np.array([0.0, 10.0, 15.0, 20.0, 60.0])
    s = fovea_scale(e, 10.0, 5.0, 1.0, 16.0)
    assert s[0] == s[1] == 1.0 and 1.0 < s[2] < s[3] and s[4] == 16.0
    assert s[2] == pytest.approx(np.exp(0.5))            # one sigma past the fovea: S = e^-1/2
    assert np.all(fovea_scale(e, 10.0, 0.0, 1.0, 16.0) == 1.0)   # sigma 0: uniform


def test_ladder_round_trip_pareto_front_and_errors(tmp_path):
    pts = [OperatingPoint("a", mbps=10, flip=0.10), OperatingPoint("b", mbps=5, flip=0.12),
           OperatingPoint("c", mbps=8, flip=0.13), OperatingPoint("d", mbps=20, flip=0.10)]
    assert [p.name for p in pareto_front(pts)] == ["b", "a"]     # c: dearer and worse than b; d: dearer than a
    path = tmp_path / "ladder.json"
    path.write_text(Ladder(tuple(pareto_front(pts)), command="cmd").to_json())
    back = load_ladder(path)
    assert [p.name for p in back.points] == ["b", "a"] and back.command == "cmd" and back.index("a") == 1
    path.write_text(json.dumps({"points": [{"name": "x", "mbps": 5}, {"name": "y", "mbps": 4}]}))
    with pytest.raises(LadderError, match="strictly rising mbps"):
        load_ladder(path)
    path.write_text("{")
    with pytest.raises(LadderError, match="not JSON"):
        load_ladder(path)
    with pytest.raises(LadderError, match="no point named"):
        back.index("z")


def test_ladder_points_keep_the_best_of_each_frame_rate():
    pts = [OperatingPoint("slow-cheap", fps=10, mbps=4, flip=0.08), OperatingPoint("fast-cheap", fps=30, mbps=5,
                                                                                   flip=0.09),
           OperatingPoint("fast", fps=30, mbps=10, flip=0.07), OperatingPoint("slow-worse", fps=10, mbps=6, flip=0.10)]
    # the front of all points would drop fast-cheap (slow-cheap is cheaper and better without a rate limit)
    assert [p.name for p in pareto_front(pts)] == ["slow-cheap", "fast"]
    assert [p.name for p in ladder_points(pts)] == ["slow-cheap", "fast-cheap", "fast"]


def test_on_a_slow_link_the_controller_prefers_fresh_frames():
    ladder = Ladder((OperatingPoint("slow", fps=6, mbps=4, flip=0.08), OperatingPoint("fast", fps=30, mbps=4.5,
                                                                                      flip=0.09),
                     OperatingPoint("top", fps=30, mbps=20, flip=0.07)))
    c = RateController(RateConfig(ladder))
    # 5 Mbit/s: a 6 fps frame (0.67 Mbit) takes 133 ms to cross, and is shown 167 ms: too old; 30 fps frames fit
    assert c.expected_age_s(0, 1 / 30, 5.0) > 0.1 > c.expected_age_s(1, 1 / 30, 5.0)
    assert c._best_fitting(4.9, 1 / 30, 5.0) == 1
    assert c._best_fitting(4.9, 1 / 30, None) == 0       # link unknown: the best FLIP that fits
    # nothing fresh under the target (0.85 x 5.0): the fast point, within half the margin to the link, beats the
    # slow one that fits the target but whose frames are shown old
    assert c._best_fitting(4.25, 1 / 30, 5.0) == 1
    assert c._best_fitting(4.25, 1 / 30, 4.3) == 0       # ... but not past that


def test_the_shipped_ladder_is_measured():
    ladder = load_ladder()
    assert len(ladder) >= 4 and "quadcast" in ladder.command and "bench ladder" in ladder.command
    assert all(p.mbps is not None and p.flip is not None for p in ladder.points)
    assert [p.name for p in ladder_points(list(ladder.points))] == [p.name for p in ladder.points]
    assert ladder[-1].mbps > 3 * ladder[0].mbps          # a range wide enough to fit links far apart
    assert {p.fps for p in ladder.points} >= {30, 15}


# ------------------------------------------------------------------------------------ the controller alone

def _controller(**kw) -> RateController:
    return RateController(RateConfig(LADDER, **kw))


def test_start_point_ceiling_and_slow_start_window():
    assert _controller().point.name == "p1"                       # the best fitting start_mbps (6)
    assert _controller(start_mbps=100).point.name == "p7"
    c = _controller(start_mbps=100, target_mbps=13)
    assert c.point.name == "p3"                                   # the ceiling wins
    # no report yet: at most initial_frames frames in flight
    for i in range(4):
        assert c.may_start(i / 30, 1 / 30)
        c.frame_sent(i / 30, i, 50_000)
    assert not c.may_start(4 / 30, 1 / 30) and c.state.frames_paced == 1
    # a frame sent 2 s ago with no report at all: the client does not report, nothing is paced any more
    assert c.may_start(2.2, 1 / 30)


def _feed(c: RateController, rate_mbit: float, seconds: float, delay: float = 0.05, interval: float = 1 / 30,
          tick: float | None = None, size_of=None, late=None, seed: int = 0):
    """Frames of the controller's chosen point through a link of `rate_mbit` with a one-way `delay`: the server starts
    one at most every `interval` (the frame interval the controller is told), asking `may_start` every `tick` (default
    `interval`); `size_of(index, frame_id)` -> (bytes, self-contained), by default the ladder's bytes per frame at 30
    fps; reports come back after another `delay`. `late(rng)` -> (s, s) adds to each frame's arrival and report (the
    link's jitter and the event loops' lateness; arrivals keep their order)."""
    rng = np.random.default_rng(seed)
    free = last_arrive = next_frame = t = 0.0
    pending, fid = [], 0
    c.history = []
    while t < seconds:
        while pending and pending[0][0] <= t:
            t_report, entry = pending.pop(0)
            c.report(t_report, [entry], interval)
        if t >= next_frame - 1e-9 and c.may_start(t, interval):
            index = c.choose(t, interval)
            c.history.append((t, index))
            size, self_contained = size_of(index, fid) if size_of else (int(LADDER[index].mbps * 1e6 / 8 / 30), False)
            c.frame_sent(t, fid, size, index, self_contained=self_contained)
            free = max(free, t) + size * 8 / (rate_mbit * 1e6)
            arrive_late, report_late = late(rng) if late else (0.0, 0.0)
            last_arrive = max(free + delay + arrive_late, last_arrive)
            pending.append((last_arrive + delay + report_late, (fid, size, last_arrive)))
            pending.sort()
            fid, next_frame = fid + 1, t + interval
        t += tick or interval
    return c


def test_overuse_moves_down_to_what_fits_and_measures_the_capacity():
    c = _feed(_controller(start_mbps=100), 12.0, 3.0)
    assert c.state.decreases >= 1
    assert c.state.capacity_mbps == pytest.approx(12.0, rel=0.15)
    late = [LADDER[i].mbps for t, i in c.history if t > 1.5]
    assert np.mean([m <= 12.0 for m in late]) > 0.75               # the point fits the link (but for brief probes)
    assert np.mean([m >= 8.0 for m in late]) > 0.75                # ... and is not needlessly low


def test_hysteresis_does_not_retry_a_failed_rate_at_once():
    c = _feed(_controller(start_mbps=100), 12.0, 3.0)
    index, increases = c.index, c.state.increases
    # the next point up (16) failed at 12 Mbit/s: within hold_up_s and the headroom's growth it is not tried again
    t = 3.0
    assert c.choose(t, 1 / 30) == index
    assert c.headroom_mbps(t) < LADDER[index + 1].mbps or c.state.increases == increases


def test_the_first_decision_goes_by_what_the_link_delivered():
    """A link that drops to 12 Mbit/s under frames that each arrive late but never wait for the one before (no
    spacing to measure): the first decision takes the rate the late frames were delivered at, not a guess."""
    c = _controller(start_mbps=100)
    top = c.index
    sends = [(i / 30, i, 20_000, i / 30 + 0.052) for i in range(10)]          # 100 Mbit/s: 1.6 ms a frame
    sends += [(0.40, 10, 50_000, 0.40 + 0.05 + 50_000 * 8 / 12e6),            # 12 Mbit/s from here on
              (0.45, 11, 150_000, 0.45 + 0.05 + 150_000 * 8 / 12e6)]
    for t, fid, size, _ in sends:
        c.frame_sent(t, fid, size, top)
    for t, fid, size, arrive in sends:
        c.report(arrive + 0.05, [(fid, size, arrive)], 1 / 30)
    assert c._capacity_mbps() == (None, None)              # frame 11 was sent after frame 10 had left
    assert c.state.overuse and c.state.decreases == 1
    assert 0.8 * 12 < c.state.capacity_mbps <= 12.0        # 200 kB over the 148 ms the link was busy with them
    assert c.predicted_mbps(c.index, 1 / 30) <= 0.85 * c.state.capacity_mbps < c.predicted_mbps(top, 1 / 30) / 2
    assert c.headroom_mbps(0.70) == pytest.approx(c.state.capacity_mbps, rel=0.05)


def test_a_queue_longer_than_the_measuring_window_still_gets_decisions():
    """Frames of 100 kB every 1/30 s (24 Mbit/s) into a link of 16 Mbit/s that falls to 8 after 20 frames: every
    frame waits behind the one before, so the run the link's rate is measured from fills the last 2 * trend_frames
    frames and then slides. Each newly queued frame is news (before, a decision needed the run to change its
    length, so none came once it filled the window): the controller follows the second drop to a point that fits."""
    c = _controller(start_mbps=100)
    top, size, free, events = c.index, 100_000, 0.0, []
    for fid in range(40):
        t = fid / 30
        free = max(free, t) + size * 8 / ((16.0 if fid < 20 else 8.0) * 1e6)
        events += [(t, "sent", fid), (free + 0.05 + 0.05, "report", (fid, size, free + 0.05))]
    moved = []                                  # the frames whose report moved the controller
    for t, kind, what in sorted(events, key=lambda e: e[0]):
        if kind == "sent":
            c.frame_sent(t, what, size, top)    # (all at one point: the decisions alone are under test)
        else:
            index = c.index
            c.report(t, [what], 1 / 30)
            if c.index != index:
                moved.append(what[0])
    assert c.state.capacity_mbps == pytest.approx(8.0, rel=0.1)
    assert any(fid >= 20 for fid in moved)     # the run had filled the window long before frame 20
    assert c.predicted_mbps(c.index, 1 / 30) <= c.config.backoff * c.state.capacity_mbps


# ---------------------------------------------------------------------------- through the replay driver

def _run(seconds: float, adapt: bool = True, scale: float = 1.0, start_mbps: float = 10.0, **link):
    cfg = ReplayConfig(latency_ms=LATENCY_MS, jitter_ms=20.0, seed=1,
                       rate=RateConfig(LADDER, start_mbps=start_mbps) if adapt else None, **link)
    server = StubServer(size=100_000, every=5, scale=scale, first_reference=True)
    return replay(resolve_trace("builtin:walk"), server, StubClient(), cfg, int(seconds * 60))


def _ages(totals, t0: float, t1: float) -> np.ndarray:
    return np.array([a for t, a, _ in totals.ages if t0 <= t < t1 and np.isfinite(a)])


def test_a_fixed_link_gets_the_best_point_that_fits_and_fresh_frames():
    # frames 2x bigger than the ladder says (another size, another scene): the controller goes by what it sees
    for scale in (1.0, 2.0):
        totals = _run(6.0, scale=scale, rate_mbit=20.0)
        late = [f for f in totals.sent if f.t_sent > 2.0]
        sent = sum(f.bytes for f in late) * 8 / (late[-1].t_sent - late[0].t_sent) / 1e6
        assert sent <= 20.0 and sent > 10.0, sent
        assert np.mean(_ages(totals, 2.0, 6.0)) < BOUND_MS
        assert np.mean([a for _, a, _ in totals.ages if np.isfinite(a)]) < BOUND_MS
        assert totals.rate.capacity_mbps == pytest.approx(20.0, rel=0.25)


def test_without_adaptation_a_slow_link_queues_and_frames_get_old():
    totals = _run(4.0, adapt=False, rate_mbit=20.0)
    assert np.mean(_ages(totals, 2.0, 4.0)) > 3 * BOUND_MS


def test_a_step_down_and_up_is_followed_within_half_a_second(monkeypatch):
    step = trace_from_schedule([(2.0, 100.0), (2.0, 15.0), (2.0, 100.0)], "step")
    decisions = []                                                # (when, the point) after every report
    report = RateController.report

    def recording_report(self, now, entries, frame_interval_s):
        report(self, now, entries, frame_interval_s)
        decisions.append((now, self.index))
    monkeypatch.setattr(RateController, "report", recording_report)
    totals = _run(6.0, rate_trace=step, start_mbps=100.0)
    points = [(f.t_sent, f.point_index) for f in totals.sent]
    top_before = max(i for t, i in points if 1.0 < t < 2.0)
    assert LADDER[top_before].mbps > 30                           # it climbed while the link was fast
    # down: the controller goes to a lower point within 0.5 s of the step (its frames leave once what the fast link
    # left in flight has crossed), and frames are fresh again within 0.5 s
    assert min(i for t, i in decisions if 2.0 < t <= 2.5) < top_before
    assert min(i for t, i in points if 2.0 < t <= 2.75) < top_before
    slow = [f for f in totals.sent if 2.5 < f.t_sent < 4.0]      # at most brief probes above what fits
    assert sum(f.bytes for f in slow) * 8 / 1.5 / 1e6 <= 15.0
    assert np.mean([LADDER[f.point_index].mbps <= 15 for f in slow]) > 0.75
    assert np.mean(_ages(totals, 2.5, 4.0)) < BOUND_MS
    assert max(_ages(totals, 2.6, 4.0)) < 2 * BOUND_MS
    # up: fresh frames within 0.5 s, and the controller climbs again
    assert np.mean(_ages(totals, 4.5, 6.0)) < BOUND_MS
    assert max(i for t, i in points if t > 4.5) > max(i for t, i in points if 3.0 < t < 4.0)


def test_the_servers_own_settings_as_a_point():
    own = own_point(18.0, 0.25, 4)
    assert own.name == OWN_POINT and (own.crf, own.viewcell_m, own.reference_every, own.fps) == (18.0, 0.25, 4, 30.0)
    assert own.same_settings(OperatingPoint(crf=18.0, viewcell_m=0.25, reference_every=4))   # the other knobs' defaults
    assert (own.hidden_layers, own.quad_scale, own.foveated, own.mbps) == (3, 1.0, False, None)
    assert RateConfig(LADDER, own=own).points == LADDER.points + (own,)
    assert own_point(None, 0.25, 4).crf == 20.0                                # quasar's default CRF
    rc = session_rate(LADDER, 12.0, None, 0.5, 5)                              # what live and replayed sessions get
    assert rc.target_mbps == 12.0 and rc.own == own_point(20.0, 0.5, 5, LADDER.fps)
    with pytest.raises(ValueError, match="already has a point named 'p3'"):
        RateConfig(LADDER, own=replace(own, name="p3"))
    with pytest.raises(ValueError, match="RateConfig.own: expected an OperatingPoint"):
        RateConfig(LADDER, own="crf=18")


def _own_size(i, fid):
    """Frame bytes at 30 fps: the ladder's, and the server's own settings (index 8) 1.4 times the best point's."""
    mbps = LADDER[i].mbps if i < len(LADDER) else 1.4 * LADDER[-1].mbps
    return int(mbps * 1e6 / 8 / 30), False


def test_the_servers_own_settings_come_only_after_a_calm_spell_at_the_ladders_best_point():
    """Above the ladder: what the server sends unadapted, entered from the ladder's best point once it has run
    `own_hold_s` without a change or an overuse (its frames are the biggest in flight when a link drops), and then
    kept on a link that carries it. Without `own` the controller stays on the ladder."""
    own = own_point(18.0, 0.5, 5)
    c = _feed(_controller(start_mbps=100, own=own), 300.0, 6.0, size_of=_own_size)
    best = c._best
    assert c._best == len(LADDER) - 1 and c.own_index == len(LADDER) and c.points[c.own_index] is own
    reached_best = min(t for t, i in c.history if i == best)
    first_own = min(t for t, i in c.history if i == c.own_index)
    assert first_own >= reached_best + c.config.own_hold_s
    assert first_own < reached_best + c.config.own_hold_s + 0.5
    assert all(i == c.own_index for t, i in c.history if t > first_own)       # the link carries it: kept
    assert c.state.decreases == 0 and c.point is own
    plain = _feed(_controller(start_mbps=100), 300.0, 6.0, size_of=_own_size)
    assert max(i for _, i in plain.history) == len(LADDER) - 1
    # its rate before it has been seen: own_guess times the best point's as seen
    fresh = _feed(_controller(start_mbps=100, own=own), 300.0, 0.5, size_of=_own_size)
    assert fresh.predicted_mbps(fresh.own_index, 1 / 30) == pytest.approx(
        1.5 * fresh.predicted_mbps(best, 1 / 30))


def test_the_servers_own_settings_are_guessed_from_the_best_point_not_the_nearest_one():
    """Before they are seen, the server's own settings are predicted at own_guess times the ladder's best point's
    prediction, also where another point's frames are nearer their guessed size. Here a 15 fps point's frames
    (200 kB in the ladder's terms, against 125 kB for the best point and 187.5 kB for own) came twice their ladder
    size: scaled from it, own would be predicted at 3 times the best point's rate, over the slow start's limit of 2."""
    ladder = Ladder((OperatingPoint("f15", crf=28, fps=15, mbps=24.0, flip=0.10),
                     OperatingPoint("f30", crf=23, mbps=30.0, flip=0.05)), command="test ladder")
    c = RateController(RateConfig(ladder, start_mbps=100, own=own_point(18.0, 0.5, 5)))
    best = c._best
    assert ladder[best].name == "f30"
    for fid, (index, size) in enumerate([(0, 400_000)] * 5 + [(best, 125_000)] * 5):
        c.frame_sent(fid / 30, fid, size, index, self_contained=fid % 5 == 0)
    assert c.predicted_mbps(best, 1 / 30) == pytest.approx(30.0)
    assert c.predicted_mbps(c.own_index, 1 / 30) == pytest.approx(1.5 * 30.0)


def test_a_link_that_drops_under_the_servers_own_settings_sends_the_controller_back_to_the_ladder():
    """Through the replay: the server's own settings on a fast link, then at 5 s a drop to 40 Mbit/s (under their
    1.5 x 64): back on a ladder point that fits within half a second, and frames fresh again."""
    step = trace_from_schedule([(5.0, 300.0), (2.0, 40.0)], "drop")
    own = replace(own_point(18.0, 0.5, 5), mbps=1.5 * LADDER[-1].mbps)     # the stub server's frame sizes
    cfg = ReplayConfig(latency_ms=LATENCY_MS, jitter_ms=20.0, seed=1, rate_trace=step,
                       rate=RateConfig(LADDER, start_mbps=100.0, own=own))
    totals = replay(resolve_trace("builtin:walk"), StubServer(size=100_000, every=5, first_reference=True),
                    StubClient(), cfg, 7 * 60)
    points = [(f.t_sent, f.point_index) for f in totals.sent]
    own_index = len(LADDER)
    assert any(i == own_index for t, i in points if t < 5.0)
    assert all(i < own_index and LADDER[i].mbps <= 40.0 for t, i in points if t > 5.5)
    assert np.mean(_ages(totals, 5.5, 7.0)) < BOUND_MS
    assert totals.sent[-1].point != OWN_POINT and any(f.point == OWN_POINT for f in totals.sent)


_SLOW = dict(   # a server that finishes a frame every 134 ms (the point allows 30 fps), asking at every 60 Hz pose, over
    # a link with 20+-10 ms of delay, each arrival and report later still by the two event loops' own lateness
    # (exponential, mean 30 and 15 ms), as live on two busy cores; every fifth frame self-contained, 3x a residual one
    delay=0.02, interval=0.134, tick=1 / 60,
    size_of=lambda i, fid: (int(LADDER[i].mbps * 1e6 / 8 / 30 * (1.2 if fid % 5 == 0 else 0.4)), fid % 5 == 0),
    late=lambda rng: (rng.uniform(-0.01, 0.01) + rng.exponential(0.03), rng.exponential(0.015)))


def test_a_server_slower_than_the_link_is_not_taken_for_a_slow_link():
    """The top point's frames, made at 7.5 a second, fill 45% of the link. The pacing's ack clock holds a frame now
    and then until the one before is reported (a round trip is about a frame interval here), and the reports of the
    last 0.5 s hold three or four frames: what they delivered is what the server made, not what the link carries.
    The controller keeps the top point; a frame held back counts once however often it is asked for."""
    for seed in range(4):
        c = _feed(_controller(start_mbps=100), 20.0, 20.0, **_SLOW, seed=seed)
        assert c.state.frames_paced > 0                            # frames were held back ...
        assert c.state.decreases == 0 and c.index == len(LADDER) - 1, seed    # ... and nothing stepped down
    # asked at every pose while one frame waits: one frame held back
    c = _controller()
    for i in range(4):
        c.frame_sent(i / 30, i, 50_000)
    assert not any(c.may_start(0.2 + k / 60, 1 / 30) for k in range(5))
    assert c.state.frames_paced == 5 and len(c._paced) == 1
    c.frame_sent(0.3, 4, 50_000)
    assert not c.may_start(0.31, 1 / 30) and len(c._paced) == 2


def test_a_client_that_never_reports_is_not_held_back():
    s = ServerSession(ServerSessionConfig(clock_offset_s=0.0, rate=RateConfig(LADDER)))
    started = 0
    for k in range(150):                                           # 5 s of poses, frames sent, no report ever
        t = k / 30
        d = s.pose_received(t, t, np.array([0.0, 1.6, 0.0]), np.array([0.0, 0.0, 0.0, 1.0]))
        if d is not None:
            started += 1
            s.frame_encoded(t, f"f{k}", True, 0.0)
            s.next_to_send()
            s.frame_sent(t, k, 60_000)
    assert started >= 90          # after lost_after_s (2 s) without any report, every pose starts a frame
    assert s.counters.reports == 0


# ------------------------------------------------------------------------------------------ session parts

def test_a_fixed_point_caps_the_frame_rate_through_the_timer():
    point = OperatingPoint("slow", fps=10)
    s = ServerSession(ServerSessionConfig(clock_offset_s=0.0, point=point))
    p, q = np.array([0.0, 1.6, 0.0]), np.array([0.0, 0.0, 0.0, 1.0])
    d = s.pose_received(0.0, 0.0, p, q)
    assert d.point is point and d.point_index is None
    s.frame_encoded(0.01, "f0", True, 0.01)
    assert s.pose_received(1 / 30, 1 / 30, p, q) is None           # 10 fps: the next frame waits
    assert s.timer() == pytest.approx(0.1)
    assert s.handle_timer(0.1).started == 0.1
    with pytest.raises(ValueError, match="exclude each other"):
        ServerSessionConfig(point=point, rate=RateConfig(LADDER))


def test_the_client_reports_each_arrival():
    c = ClientSession()
    r = c.frame_arrived(1.25, 7, 12_345)
    assert isinstance(r, SendReport) and r.entries == ((7, 12_345, 1.25),)
    assert c.counters.frames_arrived == 1


def test_a_points_rate_counts_its_self_contained_frame_once_per_reference_cycle():
    # the first frame at a point is self-contained (a new CRF restarts the stream) and three times a residual's: the
    # prediction is the cycle's mean (one such frame in reference_every = 5), not an average dominated by it
    c = _controller()
    i = c.index
    c.frame_sent(0.0, 0, 300_000, i, self_contained=True)
    c.frame_sent(0.1, 1, 100_000, i)
    assert c.bytes_per_frame(i) == pytest.approx((300_000 + 4 * 100_000) / 5)
    assert c.predicted_mbps(i, 1 / 30) == pytest.approx(140_000 * 8 * 30 / 1e6)
    # a point seen only through its self-contained frame: its residuals at the ratio seen elsewhere (1/3 here)
    j = i + 1
    c.frame_sent(0.2, 2, 600_000, j, self_contained=True)
    assert c.bytes_per_frame(j) == pytest.approx((600_000 + 4 * 200_000) / 5)
    # an unused point: the nearest used one scaled by the ladder's ratio of the two
    k = j + 1
    assert c.bytes_per_frame(k) == pytest.approx(c.bytes_per_frame(j) * LADDER[k].mbps / LADDER[j].mbps)


def test_bench_ladder_measures_again_what_other_code_measured(tmp_path):
    """`bench ladder` reuses an earlier run's rows only when the same code measured them: the code's fingerprint
    follows every source and shader byte (not data files), and a row from other code is not taken."""
    import json

    from quadcast.cli.bench import code_fingerprint, reusable_ladder_rows
    tree = tmp_path / "code"
    (tree / "render").mkdir(parents=True)
    (tree / "mod.py").write_text("x = 1\n")
    (tree / "render" / "stage.comp").write_text("void main() {}\n")
    first = code_fingerprint(tree)
    assert code_fingerprint(tree) == first and len(first) == 16
    (tree / "render" / "ladder.json").write_text("{}")                   # data: not code
    assert code_fingerprint(tree) == first
    (tree / "render" / "stage.comp").write_text("void main() { }\n")    # one shader byte
    assert code_fingerprint(tree) != first
    assert len(code_fingerprint()) == 16                                  # the installed package

    run = {"size": [640, 360], "frames": 48, "code": first}
    rows = [{"name": "a", "run": run}, {"name": "b", "run": dict(run, code="0" * 16)}]
    (tmp_path / "all.json").write_text(json.dumps(rows))
    assert list(reusable_ladder_rows(tmp_path / "all.json", run)) == ["a"]
    assert reusable_ladder_rows(tmp_path / "missing.json", run) == {}
