"""``quadcast demo``: the live system as three processes on loopback -- server, link (20±10 ms), client.

By default the client follows the built-in walk through the built-in courtyard; :class:`DemoView` names another
scene and trace (a QUASAR trace file re-anchored into the scene, from a start time or its fastest window), so the
live run and its virtual-time twin can be compared on scenes and head motion the defaults do not show.

:class:`Child` runs one ``quadcast`` subcommand as a child process, collects its stdout lines (a reader thread)
and its stderr in a log file, and can wait for a line matching a pattern (``... listening on HOST:PORT``). The
children die with their parent (``PR_SET_PDEATHSIG`` on Linux) and :func:`run_demo` stops them on any exit.
The tests start their processes the same way.
"""
from __future__ import annotations

import functools
import json
import math
import os
import re
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, replace
from pathlib import Path

from quadcast.render.worker import die_with_parent

__all__ = ["Child", "DemoView", "client_cpus", "quadcast_argv", "run_demo", "LISTENING", "TRANSPORTS"]

LISTENING = re.compile(r"listening on ([0-9.]+|localhost):(\d+)")
"""What a ready server or link prints; group 2 is the port."""


def quadcast_argv(*args: str) -> list[str]:
    """The command line running ``quadcast ARGS`` with this interpreter."""
    return [sys.executable, "-m", "quadcast", *map(str, args)]


def _die_with_parent(increment: int = 0, cpus: frozenset[int] | None = None) -> None:
    # runs in the child between fork and exec; then lowers its priority by `increment` and keeps it on `cpus` (all
    # its threads: they inherit both)
    die_with_parent(signal.SIGTERM)
    if increment:
        os.nice(increment)
    if cpus is not None:
        os.sched_setaffinity(0, cpus)


class Child:
    """A child process whose stdout lines are kept (and optionally echoed) and whose stderr goes to ``log``; with
    ``nice`` > 0 it runs that much below this process's priority, and with ``cpus`` only on those CPUs (all its
    threads: both are set before exec; Linux)."""

    def __init__(self, name: str, argv: list[str], log: Path | None = None, echo: bool = False,
                 env: dict | None = None, nice: int = 0, cpus: set[int] | None = None) -> None:
        if not 0 <= nice <= 19:
            raise ValueError(f"Child {name!r}: nice must be 0..19, got {nice}")
        linux = sys.platform.startswith("linux")
        if cpus is not None:
            allowed = os.sched_getaffinity(0) if linux else set()
            if not cpus or not set(cpus) <= allowed:
                raise ValueError(f"Child {name!r}: cpus must be a non-empty subset of this process's CPUs "
                                 f"{sorted(allowed)}, got {sorted(cpus)}")
        self.name, self.argv, self.echo = name, argv, echo
        self.lines: list[str] = []
        self._cond = threading.Condition()
        self.log_path = log
        self._log = open(log, "w") if log is not None else subprocess.DEVNULL
        full_env = {**os.environ, "PYTHONUNBUFFERED": "1", **(env or {})}
        self.proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=self._log, stdin=subprocess.DEVNULL,
                                     text=True, env=full_env,
                                     preexec_fn=functools.partial(_die_with_parent, nice,
                                                                  None if cpus is None else frozenset(cpus))
                                     if linux else None)
        self._reader = threading.Thread(target=self._read, name=f"{name}-stdout", daemon=True)
        self._reader.start()

    def _read(self) -> None:
        for line in self.proc.stdout:
            line = line.rstrip("\n")
            with self._cond:
                self.lines.append(line)
                self._cond.notify_all()
            if self.echo:
                print(f"[{self.name}] {line}", flush=True)
        with self._cond:
            self._cond.notify_all()

    @property
    def pid(self) -> int:
        return self.proc.pid

    def stderr_tail(self, n: int = 20) -> str:
        if self.log_path is None or not Path(self.log_path).exists():
            return "(stderr not kept)"
        return "\n".join(Path(self.log_path).read_text(errors="replace").splitlines()[-n:])

    def wait_for_log(self, pattern: str | re.Pattern, timeout: float) -> re.Match:
        """The first match of ``pattern`` in the process's log (its stderr, ``log``), waiting up to ``timeout`` s for
        it to be written (a server logs a session's end after its client has gone); RuntimeError if it is not."""
        if self.log_path is None:
            raise RuntimeError(f"{self.name}: no log kept")
        rx = re.compile(pattern) if isinstance(pattern, str) else pattern
        deadline = time.monotonic() + timeout
        while True:
            m = rx.search(Path(self.log_path).read_text(errors="replace"))
            if m:
                return m
            if time.monotonic() > deadline:
                raise RuntimeError(f"{self.name}'s log has no {rx.pattern!r} after {timeout:g} s")
            time.sleep(0.2)

    def wait_for(self, pattern: str | re.Pattern, timeout: float) -> re.Match:
        """The first stdout line matching ``pattern`` (waits up to ``timeout`` s); RuntimeError if the process
        exits first or the time runs out."""
        rx = re.compile(pattern) if isinstance(pattern, str) else pattern
        deadline = time.monotonic() + timeout
        seen = 0
        with self._cond:
            while True:
                for line in self.lines[seen:]:
                    m = rx.search(line)
                    if m:
                        return m
                seen = len(self.lines)
                left = deadline - time.monotonic()
                if self.proc.poll() is not None and not self._reader.is_alive():
                    raise RuntimeError(f"{self.name} exited with code {self.proc.returncode} before printing "
                                       f"{rx.pattern!r}; stderr:\n{self.stderr_tail()}")
                if left <= 0:
                    raise RuntimeError(f"{self.name} did not print {rx.pattern!r} within {timeout:g} s; "
                                       f"stderr:\n{self.stderr_tail()}")
                self._cond.wait(min(left, 0.5))

    def wait(self, timeout: float) -> int:
        """Wait for the process to exit (TimeoutExpired after ``timeout``); returns its exit code."""
        code = self.proc.wait(timeout)
        self._reader.join(5)
        return code

    def stop(self, timeout: float = 10.0) -> int | None:
        """SIGTERM, then SIGKILL after ``timeout``; returns the exit code."""
        if self.proc.poll() is None:
            try:
                self.proc.send_signal(signal.SIGTERM)
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5)
        self._reader.join(5)
        if self._log is not subprocess.DEVNULL:
            self._log.close()
        return self.proc.returncode

    def kill(self) -> None:
        """SIGKILL at once (a crash, as far as the peers can tell)."""
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(10)


CLIENT_NICE = 19
"""How far below the server and link the demo's client runs. On a real deployment the headset has a processor of
its own; here the client shares the server's two cores, and at equal priority its 60 Hz display loop took a third
of the server's frame rate (README, "Live system"). A busy loop on the client's core at nice 10 still made the
server's frame about a tenth slower, at 19 half that (the server's rasterizer threads wait for each other at every
pass). In the demo at 19 the server sent 8.5-9.7 frames a second against 7.9-8.5 at 10, the client showing 21-24
frames a second against 23-26 (docs/speed.md, stop 52)."""

CLIENT_CORES = 1
"""How many of this machine's cores the demo's client may run on (the last ones; 0: all of them). Kept to one core,
as a headset's processor is its own, it never takes both of a two-core machine's cores from the server, whose
rasterizer threads wait for each other: in alternating runs here the server sent 8.0-8.6 frames a second (one run
7.3) instead of 7.3-7.5, and the client showed as many frames as before (docs/speed.md, stop 48)."""


TRANSPORTS = ("tcp", "webrtc")
"""What the demo's three processes may speak: TCP (the default) or WebRTC (``quadcast link --webrtc`` then shapes
every datagram between the peers)."""

DEMO_SECONDS = 10.0
"""How long the demo's client follows its trace unless told (or less, if the trace ends sooner)."""


@dataclass(frozen=True)
class DemoView:
    """What the demo's client follows: `trace` (``builtin:NAME`` or a QUASAR trace file) in `scene`, re-anchored
    with `anchor` (None, ``spawn`` or ``x,y,z[,yaw_deg]``, as ``quadcast eval --anchor``), from `start` seconds into
    it or, with ``"fastest"``, from the start of its `duration` s of fastest motion (`Trace.fastest_window`), for
    `duration` s (None: :data:`DEMO_SECONDS`, or the rest of the trace if shorter), at `size` (WxH)."""

    scene: str = "builtin:courtyard"
    trace: str = "builtin:walk"
    anchor: str | None = None
    start: float | str = 0.0
    duration: float | None = None
    size: str = "480x270"

    def resolved(self) -> "DemoView":
        """This view with `start` and `duration` in seconds, checked against the trace (clear errors: a bad trace,
        size or anchor, a start past its end, a duration longer than what is left of it)."""
        from quadcast.render.camera import parse_size
        from quadcast.render.traces import parse_anchor, resolve_trace
        parse_size(self.size)
        if self.anchor is not None:
            parse_anchor(self.anchor)
        trace = resolve_trace(self.trace)
        if self.duration is not None and not (math.isfinite(self.duration) and self.duration > 0):
            raise ValueError(f"--duration must be > 0 s, got {self.duration:g}")
        if self.start == "fastest":
            duration = min(DEMO_SECONDS, trace.duration) if self.duration is None else self.duration
            start = trace.fastest_window(duration)
        elif isinstance(self.start, str) or not (math.isfinite(self.start) and 0 <= self.start < trace.duration):
            raise ValueError(f"--start must be 'fastest' or seconds in [0, {trace.duration:.2f}) of "
                             f"{self.trace}, got {self.start!r}")
        else:
            start = float(self.start)
            rest = trace.duration - start
            duration = min(DEMO_SECONDS, rest) if self.duration is None else self.duration
            if duration > rest + 1e-9:
                raise ValueError(f"{self.trace} has {rest:.2f} s left after --start {start:g} s, less than "
                                 f"--duration {duration:g} s")
        return replace(self, start=float(start), duration=float(duration))

    def trace_args(self) -> list:
        """The client's and ``quadcast eval``'s trace options for this (resolved) view."""
        anchor = [] if self.anchor is None else ["--anchor", self.anchor]
        return ["--scene", self.scene, "--trace", self.trace, *anchor, *(["--start", str(self.start)]
                                                                         if self.start else [])]


def client_cpus(cores: int) -> set[int] | None:
    """The CPUs the demo's client runs on: the last `cores` of this process's, or None (no limit) when `cores` is 0
    or not fewer than it has, or off Linux."""
    if cores < 0:
        raise ValueError(f"client cores must be >= 0, got {cores}")
    if not cores or not sys.platform.startswith("linux"):
        return None
    allowed = sorted(os.sched_getaffinity(0))
    return set(allowed[-cores:]) if cores < len(allowed) else None


def run_demo(out: Path, quiet: bool = False, view: DemoView = DemoView(), record_every: int = 3,
             compare: bool = True, client_nice: int = CLIENT_NICE, client_cores: int = CLIENT_CORES,
             warm_up: bool = True, transport: str = "tcp") -> int:
    """Start server, link and client (the client `client_nice` below the others' priority, on `client_cores` of the
    machine's cores: `client_cpus`) on `view`'s scene and trace; print the client's figures and where the report
    is. With `compare`, then replay the same trace at the same size over the same link model in virtual time
    (:func:`virtual_twin`) and print both FLIPs: what the live system lost to this machine's speed; and once more
    with the server taking the live run's time per received frame: how much of that loss is the server's frame
    rate. `warm_up` False passes ``--no-warm-up`` to server and client. `transport` is ``tcp`` or ``webrtc`` (the
    server's, the link's and the client's; the virtual-time replays model neither)."""
    if transport not in TRANSPORTS:
        raise ValueError(f"transport must be one of {', '.join(TRANSPORTS)}, got {transport!r}")
    view = view.resolved()
    size, duration = view.size, view.duration
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    children: list[Child] = []

    def on_term(signum, frame):  # stop the children through the finally below
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGTERM, on_term)
    try:
        t0 = time.monotonic()
        no_warm_up = () if warm_up else ("--no-warm-up",)
        server = Child("server", quadcast_argv("server", "--scene", view.scene, "--port", 0, "--transport",
                                               transport, *no_warm_up, "-v"),
                       out / "server.log", echo=not quiet)
        children.append(server)
        port = int(server.wait_for(LISTENING, 120).group(2))
        link = Child("link", quadcast_argv("link", "--listen", 0, "--to", f"127.0.0.1:{port}", "--delay", "20ms",
                                           "--jitter", "10ms", *(["--webrtc"] if transport == "webrtc" else []),
                                           "-v"), out / "link.log", echo=not quiet)
        children.append(link)
        link_port = int(link.wait_for(LISTENING, 60).group(2))
        client_out = out / "client"
        cpus = client_cpus(client_cores)
        client = Child("client", quadcast_argv("client", "--connect", f"127.0.0.1:{link_port}", *view.trace_args(),
                                               "--transport", transport, "--size", size, "--duration",
                                               str(duration),
                                               "--record-every", record_every,
                                               "--label-latency", 20, "--label-jitter", 10, *no_warm_up,
                                               "--out", client_out),
                       out / "client.log", echo=not quiet, nice=client_nice, cpus=cpus)
        children.append(client)
        code = client.wait(timeout=duration + 900)
        if code != 0:
            print(f"demo: the client failed (exit {code}); its stderr:\n{client.stderr_tail()}", file=sys.stderr)
            return 1
        s = json.loads((client_out / "summary.json").read_text())
        print(f"demo: server, link (20±10 ms) and client ran as processes {server.pid}, {link.pid}, {client.pid} "
              f"on 127.0.0.1 over {transport}, the client at nice {client_nice}"
              f"{'' if cpus is None else ' on CPU ' + ','.join(map(str, sorted(cpus)))} "
              f"({time.monotonic() - t0:.0f} s)")
        print(f"demo: {s['method']} on {s['trace']} in {s['scene']} at {s['size']}, {s['duration_s']:.1f} s live: "
              f"{s['mbps']:.2f} Mbps on the socket (video {s['mbps_video']:.2f}, geometry {s['mbps_geometry']:.2f}), "
              f"{s['server_frames']} frames received = {s['server_frames'] / max(s['duration_s'], 1e-9):.1f} server "
              f"frames/s; the client showed {s['display_frames']} frames = "
              f"{s['display_frames'] / max(s['duration_s'], 1e-9):.0f} a second (its loop aims at 60)")
        from quadcast.sim.report import format_figure as fmt
        print(f"demo: FLIP {fmt(s['flip'], '.4f')}  SSIM {fmt(s['ssim'], '.4f')}  PSNR {fmt(s['psnr'], '.2f')} dB "
              f"over {s['frames']} scored frames")
        print(f"demo: report -> {client_out / 'report.html'} (summary.json, frames.csv beside it; process logs in "
              f"{out})")
        if compare:
            for child in reversed(children):      # the virtual-time run gets the machine to itself
                child.stop()
            tcp = transport == "tcp"     # the twin's downlink as the live link models it: one TCP stream
            v = virtual_twin(out / "virtual", view, quiet, tcp=tcp)
            ratio = s["flip"] / v["flip"] if s.get("flip") is not None and v.get("flip") else None
            print(f"demo: the same trace in virtual time (quadcast eval {' '.join(map(str, view.trace_args()))} "
                  f"--method quasar --latency 20 --jitter 10{' --tcp' if tcp else ''} --size {size} --frames "
                  f"{v['display_frames']} --every "
                  f"{v['every']}): {v['mbps']:.2f} Mbps, {v['server_frames'] / (v['display_frames'] / 60):.1f} "
                  f"server frames/s, FLIP {fmt(v['flip'], '.4f')}  SSIM {fmt(v['ssim'], '.4f')}  PSNR "
                  f"{fmt(v['psnr'], '.2f')} dB; live FLIP / virtual-time FLIP = {fmt(ratio, '.2f')} "
                  f"(report -> {out / 'virtual' / 'report.html'})")
            if s.get("server_frames"):
                frame_ms = round(1e3 * s["duration_s"] / s["server_frames"], 1)
                slow = virtual_twin(out / "virtual_live_rate", view, quiet, server_frame_ms=frame_ms, tcp=tcp)
                ratio = s["flip"] / slow["flip"] if s.get("flip") is not None and slow.get("flip") else None
                print(f"demo: again with the server taking the live run's {frame_ms:g} ms a frame received "
                      f"(... --server-frame-ms {frame_ms:g}): "
                      f"{slow['server_frames'] / (slow['display_frames'] / 60):.1f} server frames/s, FLIP "
                      f"{fmt(slow['flip'], '.4f')}  SSIM {fmt(slow['ssim'], '.4f')}; live FLIP / this FLIP = "
                      f"{fmt(ratio, '.2f')}: what the live run lost besides its frame rate "
                      f"(report -> {out / 'virtual_live_rate' / 'report.html'})")
        return 0
    except KeyboardInterrupt:
        print("demo: interrupted; stopping the processes", file=sys.stderr)
        return 130
    except (RuntimeError, subprocess.TimeoutExpired) as exc:
        print(f"demo: error: {exc}", file=sys.stderr)
        return 1
    finally:
        for child in reversed(children):
            child.stop()
        signal.signal(signal.SIGTERM, previous)


def virtual_twin(out: Path, view: DemoView = DemoView(), quiet: bool = False, server_frame_ms: float = 0.0,
                 tcp: bool = False) -> dict:
    """The demo's run in virtual time: quasar on `view` (its trace in its scene, its duration at 60 Hz, its size),
    20±10 ms (with `tcp`, one TCP stream's window on the downlink, as ``quadcast link`` models it), about 60 frames
    scored; the server keeps its 30 Hz whatever the machine's speed, or, with `server_frame_ms`, takes that much
    virtual time per frame. Returns its summary."""
    from quadcast.render.camera import parse_size
    from quadcast.sim.evaluate import EvalSpec, run_eval
    view = view.resolved()
    w, h = parse_size(view.size)
    frames = max(1, int(round(view.duration * 60)))
    spec = EvalSpec(scene=view.scene, trace=view.trace, anchor=view.anchor, start=view.start, method="quasar",
                    latency_ms=20.0, jitter_ms=10.0, tcp=tcp, width=w, height=h, frames=frames,
                    every=max(1, frames // 60),
                    server_frame_ms=server_frame_ms)
    return run_eval(spec, out, quiet=quiet)
