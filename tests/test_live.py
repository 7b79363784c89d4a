"""The live system as real processes on 127.0.0.1: `quadcast server`, `quadcast link`, `quadcast client`.

Every process is a child started with sim.live_demo.Child (stdout collected, stderr in a log file, killed with the
test process) and stopped in a finally; every wait has a timeout. Sizes are 320x180 and runs a few seconds, so
the figures are those of a slow software-GL machine: the checks are about correctness, not speed.
"""
from __future__ import annotations

import csv
import dataclasses
import json
import re
import socket
import struct
from pathlib import Path

import numpy as np
import pytest

from quadcast.protocol.messages import (PROTOCOL_VERSION, ErrorCode, ErrorMessage, Hello, MessageDecoder, PoseUpdate,
                               encode_message)
from quadcast.server.app import check_bind
from quadcast.cli.live import link_models, parse_hostport
from quadcast.cli.demo import LISTENING, Child, quadcast_argv
from quadcast.render.traces import Trace

ROOT = Path(__file__).resolve().parents[1]
SIZE = "320x180"
START_TIMEOUT = 120      # a process printing its "listening" line (imports, scene, GL)
RUN_TIMEOUT = 240        # a client run including its scoring


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    """One live server for the module (several tests are its concurrent / successive clients)."""
    logs = tmp_path_factory.mktemp("server")
    child = Child("server", quadcast_argv("server", "--port", 0, "--max-sessions", 4, "-v"), logs / "server.log")
    try:
        child.port = int(child.wait_for(LISTENING, START_TIMEOUT).group(2))
        yield child
    finally:
        child.stop()


def _client(port: int, out: Path, *extra, name: str = "client") -> Child:
    return Child(name, quadcast_argv("client", "--connect", f"127.0.0.1:{port}", "--size", SIZE, "--out", out,
                                     *extra), out.parent / f"{out.name}.log")


def _finish(child: Child, timeout: float = RUN_TIMEOUT) -> int:
    try:
        return child.wait(timeout)
    finally:
        child.stop()


def _summary(out: Path) -> dict:
    return json.loads((out / "summary.json").read_text())


def _check_sensible(s: dict, out: Path) -> None:
    """Figures a working run must have, whatever the machine's speed."""
    assert s["live"] is True and s["size"] == SIZE and s["method"] == "quasar"
    assert s["frames_applied"] >= 1 and s["server_frames"] >= s["frames_applied"]
    assert s["frames"] >= 1, "no displayed frame was scored"
    assert 0.0 < s["mbps"] < 1000.0
    # Mbps is what crossed the socket: at least the frames' bytes, over the run's duration
    assert s["bytes_socket"] * 8 / s["duration_s"] / 1e6 == pytest.approx(s["mbps"], rel=1e-4)
    assert s["mbps"] >= s["mbps_video"] + s["mbps_geometry"] - 1e-9
    assert 0.0 <= s["flip"] < 0.6 and 0.2 < s["ssim"] <= 1.0 and s["psnr"] > 10.0
    rows = (out / "frames.csv").read_text().strip().splitlines()
    assert len(rows) == s["frames"] + 1
    assert (out / "report.html").stat().st_size > 1000
    rec = json.loads((out / "recording.json").read_text())
    assert all((out / f["image"]).exists() for f in rec["frames"])


# ----------------------------------------------------------------------------------------- acceptance

def test_walk_through_the_link_completes_with_sensible_figures(server, tmp_path):
    """Also: the client sends its gaze trace with its poses (`--gaze`), the server's session takes it, and the
    recording scores the fovea around it."""
    link = Child("link", quadcast_argv("link", "--listen", 0, "--to", f"127.0.0.1:{server.port}", "--delay", "20ms",
                                       "--jitter", "10ms"), tmp_path / "link.log")
    gaze = tmp_path / "gaze.txt"
    gaze.write_text("0 12 5\n5000 -12 -5\n")
    try:
        link_port = int(link.wait_for(LISTENING, START_TIMEOUT).group(2))
        out = tmp_path / "walk"
        client = _client(link_port, out, "--trace", "builtin:walk", "--duration", 5, "--record-every", 6,
                         "--label-latency", 20, "--label-jitter", 10, "--gaze", gaze)
        assert _finish(client) == 0, client.stderr_tail()
    finally:
        link.stop()
    s = _summary(out)
    _check_sensible(s, out)
    frames = [f for f in json.loads((out / "recording.json").read_text())["frames"] if f["frame_id"] >= 0]
    assert frames and all(abs(f["gaze_deg"][0] - (12 - 24 * f["t"] / 5)) < 1e-6 for f in frames)
    # every pose the session took carried the gaze (the module's other clients send none; a pose the predictor
    # drops, out of order or a repeat, is not counted)
    ended = server.wait_for_log(r"session \d+ ended: (\d+) poses \(([1-9]\d*) with a gaze\)", 30)
    poses, gazes = int(ended.group(1)), int(ended.group(2))
    assert poses >= gazes >= max(30, poses - 3)
    assert s["trace"] == "builtin:walk" and s["latency_ms"] == 20 and s["jitter_ms"] == 10
    assert s["duration_s"] == pytest.approx(5.0, abs=0.5)
    assert s["reconnects"] == 0 and s["connections"] == 1 and s["frames_rejected"] == 0
    assert any("FLIP" in line and "Mbps" in line for line in client.lines)
    # the link forwarded the session's messages both ways and dropped none
    stats = next(line for line in link.lines if line.startswith("link: stopped"))
    up, down = map(int, re.search(r"up (\d+) forwarded / 0 dropped, down (\d+) forwarded / 0 dropped", stats).groups())
    assert up >= 2 and down >= 1 + s["server_frames"]


def test_adaptive_server_behind_a_slow_link_keeps_to_it(tmp_path):
    """`quadcast server --adapt` behind `quadcast link --rate`: the client reports each frame's arrival, the
    server's controller takes the reports and picks operating points, and the socket rate stays under the link's."""
    srv = Child("server", quadcast_argv("server", "--port", 0, "--adapt", "--spare-workers", 0, "-v"),
                tmp_path / "server.log")
    link = None
    try:
        port = int(srv.wait_for(LISTENING, START_TIMEOUT).group(2))
        link = Child("link", quadcast_argv("link", "--listen", 0, "--to", f"127.0.0.1:{port}", "--delay", "20ms",
                                           "--jitter", "5ms", "--rate", "0.5mbit"), tmp_path / "link.log")
        link_port = int(link.wait_for(LISTENING, START_TIMEOUT).group(2))
        out = tmp_path / "adapt"
        client = _client(link_port, out, "--trace", "builtin:walk", "--duration", 8, "--record-every", 12)
        assert _finish(client) == 0, client.stderr_tail()
    finally:
        if link is not None:
            link.stop()
        srv.stop()
    s = _summary(out)
    _check_sensible(s, out)
    assert s["mbps"] <= 0.5 * 1.02            # what crossed the client's socket: never above the link's rate
    log = Path(srv.log_path).read_text()
    ended = re.search(r"session \d+ ended: .* (\d+) receive reports", log)
    assert ended and int(ended.group(1)) >= s["server_frames"] - 2     # every frame's arrival came back
    # the controller moved off its starting point (on a loaded machine the server may be too slow to fill the link's
    # queue, so its capacity estimate may still be unknown: "?")
    assert re.search(r"operating point \S+ \(capacity ([0-9.]+|\?) Mbit/s", log)


def test_killed_client_restarts_and_resumes(server, tmp_path):
    first = _client(server.port, tmp_path / "first", "--trace", "builtin:walk", "--duration", 20, "--no-score")
    try:
        sid = int(first.wait_for(r"connected to .*session (\d+)", START_TIMEOUT).group(1))
        first.wait_for(r"first frame applied", START_TIMEOUT)
        first.kill()                                   # SIGKILL mid-stream: no Bye, socket torn down
    finally:
        first.stop()
    out = tmp_path / "second"
    second = _client(server.port, out, "--trace", "builtin:walk", "--start", 3, "--duration", 3,
                     "--record-every", 8)
    assert _finish(second) == 0, second.stderr_tail()
    s = _summary(out)
    _check_sensible(s, out)
    assert s["start_s"] == 3 and s["reconnects"] == 0
    rec = json.loads((out / "recording.json").read_text())
    assert min(f["t"] for f in rec["frames"]) >= 3.0      # it resumed from the trace time it was given
    assert server.proc.poll() is None
    # the killed client's own session ended (its line, whatever else the shared server did meanwhile)
    assert re.search(rf"session {sid} ended", Path(server.log_path).read_text())


def test_client_reconnects_when_the_link_goes_down(server, tmp_path):
    def start_link(port: int, name: str) -> tuple[Child, int]:
        link = Child(name, quadcast_argv("link", "--listen", port, "--to", f"127.0.0.1:{server.port}", "--delay",
                                         "5ms", "--jitter", "0ms"), tmp_path / f"{name}.log")
        return link, int(link.wait_for(LISTENING, START_TIMEOUT).group(2))

    link, port = start_link(0, "link1")
    out = tmp_path / "reconnect"
    client = _client(port, out, "--trace", "builtin:walk", "--duration", 8, "--record-every", 12,
                     "--retries", 40)
    relink = None
    try:
        client.wait_for(r"first frame applied", START_TIMEOUT)
        link.kill()                                    # the path to the server disappears mid-stream
        client.wait_for(r"connection lost", 30)
        relink, _ = start_link(port, "link2")          # and comes back on the same port
        client.wait_for(r"connected to .*session", 60)
        assert _finish(client) == 0, client.stderr_tail()
    finally:
        client.stop()
        link.stop()
        if relink is not None:
            relink.stop()
    s = _summary(out)
    _check_sensible(s, out)
    assert s["reconnects"] == 1 and s["connections"] == 2
    connects = [line for line in client.lines if line.startswith("client: connected")]
    assert len(connects) == 2 and connects[0] != connects[1]   # a new session on the new connection


def _lossy_seed(loss: str, down_drop=range(2, 5)) -> int:
    """A link seed whose server -> client direction drops one of the frames 1..3 (down messages 2..4; message 0
    is the Welcome) and keeps the Welcome, and whose client -> server direction keeps the Hello."""
    for seed in range(5000):
        up, down = link_models("0ms", "0ms", None, loss, seed)
        kept_up = up.send(0.0, "hello", 100) is not None
        kept_down = [down.send(0.0, k, 100) is not None for k in range(6)]
        if kept_up and kept_down[0] and kept_down[1] and not all(kept_down[i] for i in down_drop):
            return seed
    raise AssertionError("no seed found")


def test_a_slow_tcp_link_makes_the_server_drop_stale_frames_not_queue_them(server, tmp_path):
    # The server offers several Mbit/s at this size; the link carries 1. Its TCP model stops reading once a window
    # waits, the server's kernel holds what it could not send, and the server takes its next frame only when that
    # has gone: it drops the frames that went stale meanwhile, and the shown frames do not fall further and
    # further behind (with the link taking in everything they would: seconds by the end).
    link = Child("link", quadcast_argv("link", "--listen", 0, "--to", f"127.0.0.1:{server.port}", "--delay", "10ms",
                                       "--jitter", "0ms", "--rate", "1mbit", "--queue", "32k"), tmp_path / "link.log")
    try:
        link_port = int(link.wait_for(LISTENING, START_TIMEOUT).group(2))
        out = tmp_path / "slow"
        client = _client(link_port, out, "--trace", "builtin:walk", "--duration", 8, "--record-every", 6)
        assert _finish(client) == 0, client.stderr_tail()
    finally:
        link.stop()
    s = _summary(out)
    _check_sensible(s, out)
    assert s["mbps"] < 1.2
    sid = int(next(re.search(r"session (\d+)", line) for line in client.lines if "connected to" in line).group(1))
    ended = server.wait_for_log(rf"session {sid} ended: .*queue dropped (\d+) stale \+ (\d+) new", 30)
    assert int(ended.group(1)) + int(ended.group(2)) >= 5, ended.group(0)
    rows = list(csv.DictReader((out / "frames.csv").open()))
    late = [float(r["age_ms"]) for r in rows if float(r["t"]) > 5.0 and r["age_ms"]]
    assert late and np.mean(late) < 2500, late   # (a link that takes in everything: 3,800-5,900 ms)


def test_one_percent_loss_makes_the_client_resync(server, tmp_path):
    # Standing still, every frame after a reference is a residual until the next one (every 5): a lost frame
    # leaves the next residual without its predecessor, and the client has to ask for a reference.
    trace = tmp_path / "still.txt"
    times = np.arange(0.0, 12.0, 1 / 30)
    Trace("still", times, np.tile([0.0, 1.6, 6.0], (times.size, 1)), np.zeros((times.size, 3))).save(trace)
    seed = _lossy_seed("1%")
    link = Child("link", quadcast_argv("link", "--listen", 0, "--to", f"127.0.0.1:{server.port}", "--delay", "5ms",
                                       "--jitter", "0ms", "--loss", "1%", "--drop-messages", "--seed", seed),
                 tmp_path / "link.log")
    try:
        link_port = int(link.wait_for(LISTENING, START_TIMEOUT).group(2))
        out = tmp_path / "lossy"
        client = _client(link_port, out, "--trace", trace, "--duration", 8, "--record-every", 12)
        assert _finish(client) == 0, client.stderr_tail()
    finally:
        link.stop()
    s = _summary(out)
    _check_sensible(s, out)
    stats = next(line for line in link.lines if line.startswith("link: stopped"))
    assert int(re.search(r"down \d+ forwarded / (\d+) dropped", stats).group(1)) >= 1
    assert s["frames_lost"] >= 1
    assert s["reference_requests"] >= 1
    assert any("reference requested" in line for line in client.lines)
    sid = int(next(re.search(r"session (\d+)", line) for line in client.lines if "connected to" in line).group(1))
    assert re.search(rf"session {sid}: reference requested", Path(server.log_path).read_text())
    # after the resync the client applied newer frames again: the newest shown frame is past the lost one
    rec = json.loads((out / "recording.json").read_text())
    assert max(f["frame_id"] for f in rec["frames"]) >= 4
    assert s["reconnects"] == 0


def _malformed(i: int) -> bytes:
    """200 kinds of bad input, cycling through framing, type, body and order defects."""
    hello = encode_message(Hello(PROTOCOL_VERSION, "quasar", 320, 180, 60.0))
    pose = encode_message(PoseUpdate(1, 0.0, [0, 1.6, 6], [0, 0, 0, 1]))
    rng = np.random.default_rng(i)
    kinds = [
        lambda: struct.pack("<I", 0),                                   # zero length
        lambda: struct.pack("<I", 0x7FFFFFFF) + b"\x01" * 64,           # over the size cap
        lambda: struct.pack("<IB", 5, 99) + b"\x00" * 4,                # unknown type
        lambda: hello[:4] + hello[4:5] + b"\x00" * (len(hello) - 5),    # Hello with a zero size / fov
        lambda: struct.pack("<IB", 2, 1) + b"\x00",                     # truncated Hello body
        lambda: pose,                                                   # a pose before Hello
        lambda: pose[:13] + struct.pack("<d", float("nan")) + pose[21:],  # NaN in a pose, before Hello
        lambda: rng.integers(0, 256, int(rng.integers(5, 200)), dtype=np.uint8).tobytes(),  # noise
        lambda: struct.pack("<IB", 3, 5) + b"\xff\xff",                 # ReferenceRequest with a bad string
        lambda: struct.pack("<IB", 1, 7) + struct.pack("<IB", 1, 7),    # Bye, Bye before Hello
    ]
    return kinds[i % len(kinds)]()


def _send_bad(port: int, data: bytes) -> ErrorMessage | None:
    """Send ``data`` on a fresh connection; return the ErrorMessage the server answers with (None if it just
    closed)."""
    with socket.create_connection(("127.0.0.1", port), timeout=10) as s:
        s.sendall(data)
        s.shutdown(socket.SHUT_WR)
        received = b""
        while True:
            try:
                chunk = s.recv(65536)
            except (ConnectionResetError, socket.timeout):
                break
            if not chunk:
                break
            received += chunk
    msgs = MessageDecoder().feed(received) if received else []
    return next((m for m in msgs if isinstance(m, ErrorMessage)), None)


def test_malformed_messages_do_not_disturb_the_other_client(server, tmp_path):
    out = tmp_path / "steady"
    steady = _client(server.port, out, "--trace", "builtin:walk", "--duration", 7, "--record-every", 10)
    try:
        steady.wait_for(r"first frame applied", START_TIMEOUT)
        answers = [_send_bad(server.port, _malformed(i)) for i in range(200)]
        assert server.proc.poll() is None
        assert steady.proc.poll() is None, "the flood should hit the server while the steady client streams"
        code = _finish(steady)
    finally:
        steady.stop()
    assert code == 0, steady.stderr_tail()
    errors = [a for a in answers if a is not None]
    assert len(errors) >= 150, f"only {len(errors)} of 200 bad inputs got an ErrorMessage"
    assert {a.code for a in errors} <= {ErrorCode.PROTOCOL, ErrorCode.BAD_REQUEST}
    assert all(a.text for a in errors)
    s = _summary(out)
    _check_sensible(s, out)
    assert s["reconnects"] == 0 and s["connections"] == 1 and s["frames_rejected"] == 0
    # and the server still takes new clients
    again = _client(server.port, tmp_path / "again", "--trace", "builtin:static", "--duration", 2, "--no-score")
    try:
        again.wait_for(r"first frame applied", START_TIMEOUT)
        assert _finish(again) == 0
    finally:
        again.stop()


def test_stereo_client_records_both_eyes_and_scores_the_synthesized_one(server, tmp_path):
    out = tmp_path / "stereo"
    client = _client(server.port, out, "--trace", "builtin:walk", "--duration", 3, "--record-every", 5, "--stereo")
    assert _finish(client) == 0, client.stderr_tail()
    s = _summary(out)
    _check_sensible(s, out)
    st = s["stereo"]
    assert set(st) == {"ssim", "psnr", "flip", "cost_ratio"}
    assert 0.0 <= st["flip"] < 0.6 and 0.2 < st["ssim"] <= 1.0 and st["psnr"] > 10.0
    assert 0.0 < st["cost_ratio"] < 20.0
    rec = json.loads((out / "recording.json").read_text())
    assert rec["stereo"] is True and len(rec["frames"]) == s["frames"] >= 1
    from PIL import Image
    for f in rec["frames"]:
        eye = f["stereo"]
        left = np.asarray(Image.open(out / eye["left"]))
        right = np.asarray(Image.open(out / eye["right"]))
        assert left.shape == right.shape == (180, 320, 3)
        assert not np.array_equal(left, right)         # two viewpoints, not one image twice
        # the synthesized eye sits half the IPD (63 mm) to the right of the head
        assert np.linalg.norm(np.subtract(eye["position"], f["position"])) == pytest.approx(0.0315, abs=1e-4)
    assert any("stereo (synthesized right eye)" in line for line in client.lines)


def test_a_stereo_client_draws_the_head_pose_image_only_for_recorded_frames(tmp_path):
    """With --stereo the eyes are what is shown: the head-pose image (recorded and scored) is drawn only on recorded
    frames; without it, on every frame."""
    import types

    from quadcast.client.app import ClientConfig, LiveClient
    from quadcast.render.camera import Pose
    calls = []

    class Counting:
        stats: dict = {}

        def render(self, pose):
            calls.append("render")
            return np.zeros((2, 2, 3), np.uint8)

        def coverage(self):
            return types.SimpleNamespace(figures=lambda: {"holes": 0.0})

        def stereo_frame(self, pose, mode, with_rendered, masks=True):
            assert not masks                        # the masks are not recorded: not read back
            calls.append(f"stereo {with_rendered}")
            eye = np.zeros((2, 2, 3), np.uint8)
            return types.SimpleNamespace(left=eye, right=eye, other_camera=types.SimpleNamespace(pose=pose), ms={},
                                         cost_ratio=None)

    pose = Pose(np.zeros(3))
    for stereo in (True, False):
        client = LiveClient(ClientConfig(host="127.0.0.1", port=1, out=str(tmp_path), stereo=stereo),
                            lambda method, config, ctx: Counting())
        client.method_client = Counting()
        calls.clear()
        shown = client._render(pose, record=False)
        recorded = client._render(pose, record=True)
        if stereo:
            assert calls == ["stereo False", "render", "stereo True"]
            assert shown[0] is None and shown[2] is not None and recorded[0] is not None
            assert recorded[3] == {"holes": 0.0}
        else:
            assert calls == ["render", "render"] and shown[2] is None and shown[0] is not None


def test_stereo_with_a_baseline_method_fails_at_start_up(tmp_path):
    log = tmp_path / "c.log"
    child = Child("client", quadcast_argv("client", "--connect", "127.0.0.1:9", "--method", "atw", "--stereo",
                                          "--size", SIZE, "--out", tmp_path / "x"), log)
    try:
        assert child.wait(60) not in (0, None)
    finally:
        child.stop()
    text = log.read_text()
    assert "--stereo" in text and "atw" in text and "Traceback" not in text
    assert not (tmp_path / "x").exists()


def _parent_pid(pid: int) -> int:
    stat = Path(f"/proc/{pid}/stat").read_text()
    return int(stat.rsplit(")", 1)[1].split()[1])


def _workers(pid: int) -> set[int]:
    """The worker processes (multiprocessing ``spawn`` children, not its resource tracker) of process ``pid``."""
    out = set()
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                if (_parent_pid(int(entry.name)) == pid
                        and b"spawn_main" in (entry / "cmdline").read_bytes()):
                    out.add(int(entry.name))
            except (OSError, ValueError, IndexError):
                pass                                  # gone meanwhile
    return out


def _gone(pid: int, timeout: float) -> bool:
    """Whether process ``pid`` is gone and reaped (no zombie left) within ``timeout`` s."""
    import time
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if not Path(f"/proc/{pid}").exists():      # a zombie keeps its /proc entry until it is reaped
            return True
        time.sleep(0.2)
    return False


def test_each_session_encodes_in_its_own_process_and_killing_it_ends_only_that_session(tmp_path):
    import os
    import signal
    # A server of this test's own, without spare workers: each session's worker is the one new child process.
    server = Child("server", quadcast_argv("server", "--port", 0, "--spare-workers", 0), tmp_path / "server.log")
    port = int(server.wait_for(LISTENING, START_TIMEOUT).group(2))
    # The victim streams first; the steady client's session then waits for a worker process to boot (a few
    # seconds, longer while others stream), so the victim runs long enough to overlap it; it is stopped after the kill.
    victim = _client(port, tmp_path / "victim", "--trace", "builtin:walk", "--duration", 25, "--no-score")
    steady_out = tmp_path / "steady"
    steady = None
    try:
        victim.wait_for(r"first frame applied", START_TIMEOUT)
        (pid,) = _workers(server.pid)
        steady = _client(port, steady_out, "--trace", "builtin:walk", "--duration", 4, "--record-every", 8)
        steady.wait_for(r"first frame applied", START_TIMEOUT)
        (steady_pid,) = _workers(server.pid) - {pid}
        # the encoders run in processes of their own, children of the server, not in its event loop's process
        assert len({pid, steady_pid, server.pid}) == 3
        assert victim.proc.poll() is None
        os.kill(pid, signal.SIGKILL)
        victim.wait_for(r"server error 6: .*worker", 30)
        victim.wait_for(r"connection lost", 30)        # ... and the client goes on to reconnect
        victim.stop()
        assert steady.proc.poll() is None
        steady_code = _finish(steady)
        assert re.search(rf"server error 6: session worker died: .*process {pid} was killed by signal 9",
                         "\n".join(victim.lines))
    finally:
        if steady is not None:
            steady.stop()
        victim.stop()
    assert steady_code == 0, steady.stderr_tail()
    assert _gone(pid, 15), "the killed worker was not reaped"
    s = _summary(steady_out)
    _check_sensible(s, steady_out)
    assert s["reconnects"] == 0 and s["frames_rejected"] == 0
    try:
        assert server.proc.poll() is None
        # the sessions' workers end with them
        assert _gone(steady_pid, 15)
    finally:
        server.stop()


# ------------------------------------------------------------------------------------ fast unit checks

def test_pace_is_checked_and_only_for_webrtc():
    from quadcast.methods import make_server
    from quadcast.server.app import LiveServer, ServerConfig
    with pytest.raises(ValueError, match="--pace: expected a rate > 0"):
        ServerConfig(pace_mbit=0.0)
    with pytest.raises(ValueError, match="--pace paces WebRTC"):
        LiveServer(ServerConfig(pace_mbit=10.0), make_server, transport="tcp")


def test_unsent_is_checked(capsys):
    from quadcast.cli import main
    from quadcast.server.app import ServerConfig
    with pytest.raises(ValueError, match="unsent_bytes: expected >= 0"):
        ServerConfig(unsent_bytes=-1)
    assert main(["server", "--port", "0", "--unsent", "lots"]) == 2
    assert "cannot parse size 'lots'" in capsys.readouterr().err


def test_video_settings_are_checked_at_start_and_reach_the_sessions(capsys):
    """A CRF or chroma offset x264 cannot take is refused when the server starts, naming the option, not when each
    session's worker builds its encoder; a good one reaches every session's and warm-up's method config."""
    from quadcast.cli import main
    from quadcast.methods import make_server
    from quadcast.server.app import LiveServer, ServerConfig, SessionPipeline
    with pytest.raises(ValueError, match=r"--crf / --chroma-qp-offset \(quasar\): .*crf must be in \[0, 51\]"):
        ServerConfig(crf=80.0)
    with pytest.raises(ValueError, match=r"\(meshwarp\): .*chroma_qp_offset must be an integer in \[-12, 12\]"):
        ServerConfig(methods=("meshwarp",), chroma_qp_offset=13)
    assert main(["server", "--port", "0", "--chroma-qp-offset", "-20"]) == 2
    assert "chroma_qp_offset must be an integer in [-12, 12]; got -20" in capsys.readouterr().err
    server = LiveServer(ServerConfig(methods=("meshwarp", "quasar"), chroma_qp_offset=-3), make_server)
    specs = server.warm_up_specs()
    assert [s.chroma_qp_offset for s in specs] == [-3, -3]
    configs = []
    SessionPipeline(dataclasses.replace(specs[0], make_server=lambda name, renderer, config: configs.append(config)),
                    renderer=object())
    assert configs[0].chroma_qp_offset == -3 and configs[0].crf is None
    from quadcast.cli.live import video_option_help           # the options' help reads the defaults it names
    from quadcast.protocol.methods import DEFAULT_CHROMA_QP_OFFSET, DEFAULT_CRF
    assert f"quasar {DEFAULT_CRF['quasar']:g}, quadstream/meshwarp/meshwarp120/atw 23)" in video_option_help("crf")
    assert f"quasar {DEFAULT_CHROMA_QP_OFFSET['quasar']}, " in video_option_help("chroma_qp_offset")


def test_bind_and_address_checks():
    check_bind("127.0.0.1", "")
    check_bind("::1", "")
    check_bind("localhost", "")
    check_bind("0.0.0.0", "secret", tls=True)
    check_bind("0.0.0.0", "secret", allow_plaintext_token=True)
    with pytest.raises(ValueError, match="--token"):
        check_bind("0.0.0.0", "")
    with pytest.raises(ValueError, match="in clear.*--tls-cert.*--allow-plaintext-token"):
        check_bind("0.0.0.0", "secret")
    assert parse_hostport("127.0.0.1:9000") == ("127.0.0.1", 9000)
    assert parse_hostport("[::1]:9") == ("::1", 9)
    assert parse_hostport("link:9001") == ("link", 9001)
    for bad in ("9000", "host:", "host:abc", "host:70000"):
        with pytest.raises(ValueError):
            parse_hostport(bad)


def test_server_refuses_a_public_bind_without_token(tmp_path):
    child = Child("server", quadcast_argv("server", "--host", "0.0.0.0", "--port", 0), tmp_path / "s.log")
    try:
        assert child.wait(60) == 2
    finally:
        child.stop()
    assert "--token" in Path(child.log_path).read_text()


def test_wrong_token_is_refused_and_the_client_exits(tmp_path):
    server = Child("server", quadcast_argv("server", "--port", 0, "--token", "right", "--spare-workers", 0), tmp_path / "s.log")
    try:
        port = int(server.wait_for(LISTENING, START_TIMEOUT).group(2))
        client = _client(port, tmp_path / "c", "--token", "wrong", "--duration", 1, "--no-score")
        assert _finish(client, 60) == 1
        assert "token" in Path(client.log_path).read_text()
    finally:
        server.stop()


# -------------------------------------------------------------------------------- docker-compose, Dockerfile

def _read_compose(text: str) -> dict:
    """The docker-compose.yml subset used here: nested block mappings whose leaves are JSON scalars or flow
    lists (valid YAML, so `docker compose config` reads the same thing)."""
    root: dict = {}
    stack = [(-1, root)]
    for raw in text.splitlines():
        line = raw.split(" #")[0].rstrip() if not raw.lstrip().startswith("#") else ""
        if not line.strip():
            continue
        indent = len(line) - len(line.lstrip())
        key, sep, value = line.strip().partition(":")
        assert sep, f"not a mapping line: {raw!r}"
        while stack[-1][0] >= indent:
            stack.pop()
        parent = stack[-1][1]
        value = value.strip()
        if not value:
            parent[key] = {}
            stack.append((indent, parent[key]))
        elif value[0] in "[\"{":
            parent[key] = json.loads(value)
        else:
            parent[key] = value
    return root


def _expand(arg: str) -> str:
    return re.sub(r"\$\{[A-Z_]+:-([^}]*)\}", r"\1", arg)


def test_compose_services_run_real_quadcast_commands():
    import shutil
    import subprocess

    import quadcast.cli as quadcast
    compose = _read_compose((ROOT / "docker-compose.yml").read_text())
    services = compose["services"]
    assert set(services) == {"server", "link", "client"}
    assert services["server"]["build"] == "."
    assert all(s["image"] == services["server"]["image"] for s in services.values())
    parser = quadcast.build_parser()
    parsed = {name: parser.parse_args([_expand(a) for a in s["command"]]) for name, s in services.items()}
    assert {name: p.command for name, p in parsed.items()} == {"server": "server", "link": "link",
                                                              "client": "client"}
    # the wiring: client -> link -> server, by service name and port
    assert parsed["link"].to == f"server:{parsed['server'].port}"
    assert parsed["client"].connect == f"link:{parsed['link'].listen}"
    assert parsed["server"].token and parsed["client"].token == parsed["server"].token
    assert parsed["link"].delay == "20ms" and parsed["link"].jitter == "10ms"
    assert services["client"]["depends_on"] == ["link"] and services["link"]["depends_on"] == ["server"]
    # a public bind inside a container is only accepted with the token
    check_bind(parsed["server"].host, parsed["server"].token, tls=parsed["server"].tls_cert is not None,
               allow_plaintext_token=parsed["server"].allow_plaintext_token)
    if shutil.which("docker") and subprocess.run(["docker", "compose", "version"], capture_output=True).returncode == 0:
        r = subprocess.run(["docker", "compose", "-f", str(ROOT / "docker-compose.yml"), "config", "-q"],
                           capture_output=True, text=True, timeout=60)
        assert r.returncode == 0, r.stderr


def test_dockerfile_installs_the_package_and_egl():
    text = (ROOT / "Dockerfile").read_text()
    assert re.search(r"^FROM python:3\.11-slim-bookworm", text, re.M)
    for pkg in ("libegl1", "libgl1-mesa-dri", "libegl-mesa0"):
        assert pkg in text
    import tomllib
    packages = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"]
    copied = set(re.findall(r"^COPY (\w+) \1$", text, re.M))
    # every installed package's folder: quadcast/ and the layer folders its symlinks point to
    folders = {"quadcast"} | {(ROOT / "quadcast" / p.split(".")[1]).resolve().name for p in packages if "." in p}
    folders -= {"cli"}
    assert folders <= copied, f"Dockerfile does not copy {folders - copied}"
    assert re.search(r"pip install .*\.\s*$", text, re.M)
    assert re.search(r'^ENTRYPOINT \["quadcast"\]', text, re.M)
