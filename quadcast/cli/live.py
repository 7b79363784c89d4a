"""The live processes' command lines: ``quadcast server``, ``quadcast client`` and ``quadcast link``.

:func:`add_live_commands` adds the three subcommands to ``quadcast``'s parser. Each long-running process prints
one ``... listening on HOST:PORT`` line when it is ready (``--port 0`` / ``--listen 0`` pick a free port, which
that line tells), logs to stderr, and stops cleanly on SIGINT / SIGTERM.
"""
from __future__ import annotations

import asyncio
import contextlib
import logging
import signal
import sys

__all__ = ["add_live_commands", "link_models", "parse_hostport", "format_live_summary"]


def parse_hostport(text: str) -> tuple[str, int]:
    """``HOST:PORT`` (``[v6]:PORT`` too) -> (host, port)."""
    host, sep, port = str(text).rpartition(":")
    if not sep or not host:
        raise ValueError(f"expected HOST:PORT, got {text!r}")
    host = host.strip("[]")
    try:
        p = int(port)
    except ValueError:
        raise ValueError(f"expected HOST:PORT with a numeric port, got {text!r}") from None
    if not 1 <= p <= 65535:
        raise ValueError(f"port must be 1..65535, got {p} in {text!r}")
    return host, p


def _setup_logging(verbose: bool) -> None:
    logging.basicConfig(level=logging.INFO if verbose else logging.WARNING, stream=sys.stderr,
                        format="%(asctime)s %(name)s %(levelname)s: %(message)s")


async def _run_until_signal(main, on_stop=None) -> None:
    """Run ``main`` (a coroutine) until it ends or SIGINT/SIGTERM arrives; then cancel it."""
    loop = asyncio.get_running_loop()
    task = asyncio.ensure_future(main)
    stop = asyncio.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        with contextlib.suppress(NotImplementedError, RuntimeError):
            loop.add_signal_handler(sig, stop.set)
    stopper = asyncio.create_task(stop.wait())
    await asyncio.wait([task, stopper], return_when=asyncio.FIRST_COMPLETED)
    stopper.cancel()
    if not task.done():
        task.cancel()
    try:
        await task
    except asyncio.CancelledError:
        pass
    finally:
        if on_stop is not None:
            on_stop()


# ------------------------------------------------------------------------------------------------ server

def cmd_server(args) -> int:
    from quadcast.methods import make_server
    from quadcast.render.camera import parse_size
    from quadcast.server.app import LiveServer, ServerConfig, server_summary_line
    from quadcast.sim.link import parse_bytes, parse_rate_mbit
    _setup_logging(args.verbose)
    max_w, max_h = parse_size(args.max_size)
    cfg = ServerConfig(scene=args.scene, methods=tuple(m.strip() for m in args.method.split(",") if m.strip()),
                       host=args.host, port=args.port, token=args.token or "", server_hz=args.hz,
                       max_width=max_w, max_height=max_h, viewcell_m=args.viewcell,
                       reference_every=args.reference_every, crf=args.crf,
                       chroma_qp_offset=args.chroma_qp_offset, lead_ms=args.lead_ms,
                       predict=not args.no_predict, max_sessions=args.max_sessions,
                       max_message_bytes=args.max_message_bytes, worker=args.worker,
                       spare_workers=args.spare_workers, warm_up=not args.no_warm_up,
                       max_preauth=args.max_preauth, max_per_ip=args.max_per_ip,
                       handshake_timeout=args.handshake_timeout, idle_timeout=args.idle_timeout,
                       retry_after=args.retry_after, tls_cert=args.tls_cert, tls_key=args.tls_key,
                       allow_plaintext_token=args.allow_plaintext_token,
                       max_peer_connections=args.max_peer_connections, stun=args.stun,
                       pace_mbit=parse_rate_mbit(args.pace) if args.pace else None, adapt=args.adapt,
                       target_mbps=args.target_mbps, ladder=args.ladder, point=args.point,
                       unsent_bytes=parse_bytes(args.unsent, minimum=0))

    async def main() -> None:
        server = LiveServer(cfg, make_server, transport=args.transport)
        await server.start()
        print(server_summary_line(server), flush=True)
        if args.transport == "tcp":
            host = f"[{cfg.host}]" if ":" in cfg.host else cfg.host
            print(f"server: viewer page at http://{host}:{server.port}/" + ("#token=..." if cfg.token else ""),
                  flush=True)
        await server.serve_forever()

    try:
        asyncio.run(_run_until_signal(main()))
    except RuntimeError as exc:
        print(f"quadcast server: error: {exc}", file=sys.stderr)
        return 1
    print("server: stopped", flush=True)
    return 0


# ------------------------------------------------------------------------------------------------ client

def format_live_summary(s: dict) -> str:
    """One line of a live run's figures."""
    from quadcast.sim.report import format_figure as f
    return (f"{s.get('method')} on {s.get('trace')} ({s.get('transport', 'tcp')}, {s.get('size')}): "
            f"{f(s.get('mbps'), '.2f')} Mbps on the socket (video {f(s.get('mbps_video'), '.2f')}, geometry "
            f"{f(s.get('mbps_geometry'), '.2f')})  FLIP {f(s.get('flip'), '.4f')}  SSIM {f(s.get('ssim'), '.4f')}  "
            f"PSNR {f(s.get('psnr'), '.2f')} dB  [{s.get('frames')} frames scored, {s.get('server_frames')} "
            f"received, {s.get('frames_applied')} applied, {s.get('reference_requests')} reference requests, "
            f"{s.get('reconnects')} reconnects]" + (
                f"  stereo (synthesized right eye): FLIP {f(st.get('flip'), '.4f')}  SSIM {f(st.get('ssim'), '.4f')}  "
                f"PSNR {f(st.get('psnr'), '.2f')} dB  cost ratio {f(st.get('cost_ratio'), '.2f')}"
                if isinstance(st := s.get("stereo"), dict) else ""))


def cmd_client(args) -> int:
    from pathlib import Path

    from quadcast.client.app import ClientConfig, FatalServerError, LiveClient
    from quadcast.methods import make_client
    from quadcast.render.camera import parse_size
    from quadcast.sim.evaluate import evaluate_recording
    _setup_logging(args.verbose)
    host, port = parse_hostport(args.connect)
    w, h = parse_size(args.size)
    labels = {k: v for k, v in (("latency_ms", args.label_latency), ("jitter_ms", args.label_jitter),
                                ("loss", args.label_loss), ("viewcell_m", args.label_viewcell)) if v is not None}
    cfg = ClientConfig(host=host, port=port, trace=args.trace, out=args.out, scene=args.scene, method=args.method,
                       width=w, height=h, fovy_deg=args.fovy, duration=args.duration, start=args.start,
                       anchor=args.anchor, gaze=args.gaze,
                       record_every=args.record_every, token=args.token or "", transport=args.transport,
                       retries=args.retries, score=not args.no_score, stereo=args.stereo, labels=labels,
                       tls=args.tls, tls_ca=args.tls_ca, insecure=args.insecure, stun=args.stun,
                       warm_up=not args.no_warm_up)
    client = LiveClient(cfg, make_client)
    result: dict = {}

    async def main() -> None:
        result.update(await client.run())

    try:
        asyncio.run(_run_until_signal(main()))
    except (ConnectionError, FatalServerError) as exc:
        print(f"quadcast client: error: {exc}", file=sys.stderr)
        return 1
    if not result:
        print("client: interrupted", flush=True)
        return 130
    if cfg.score:
        result = evaluate_recording(cfg.out)
        print(f"client: {format_live_summary(result)}", flush=True)
        print(f"client: report: {Path(args.out) / 'report.html'}", flush=True)
    else:
        print(f"client: done, recording in {args.out} (not scored)", flush=True)
    return 0


# -------------------------------------------------------------------------------------------------- link

def link_models(delay: str, jitter: str, rate: str | None, loss: str, seed: int, rate_trace: str | None = None,
                reliable: bool = False, queue_bytes: int | None = None):
    """The (up, down) :class:`quadcast.sim.link.LinkModel` pair of ``quadcast link``: the same shaping both ways, seeds
    ``seed`` (client -> server) and ``seed + 1`` (server -> client); with ``rate_trace`` (a Mahimahi file or
    builtin:NAME) the server -> client direction follows it instead of ``rate``, from the link's start. ``reliable``
    models the TCP stream each way (segments lost and sent again) rather than dropping whole messages, with
    ``queue_bytes`` its bottleneck's drop-tail queue."""
    from quadcast.sim.proxy import parse_link_args
    from quadcast.sim.ratetrace import resolve_rate_trace
    down = parse_link_args(delay, jitter, None if rate_trace else rate, loss, seed=seed + 1, reliable=reliable,
                           rate_trace=resolve_rate_trace(rate_trace) if rate_trace else None, queue_bytes=queue_bytes)
    return parse_link_args(delay, jitter, rate, loss, seed=seed, reliable=reliable, queue_bytes=queue_bytes), down


def cmd_link(args) -> int:
    from quadcast.server.app import check_bind
    from quadcast.sim.link import parse_bytes
    from quadcast.sim.proxy import LinkProxy
    from quadcast.sim.rtc_proxy import RtcLinkProxy
    _setup_logging(args.verbose)
    to_host, to_port = parse_hostport(args.to)
    check_bind(args.host, "x" if args.public else "", allow_plaintext_token=True)   # the link holds no token
    if args.webrtc and args.drop_messages:
        raise ValueError("--drop-messages is for the TCP link; with --webrtc every loss is a datagram's")
    tcp = not args.webrtc and not args.drop_messages
    queue = parse_bytes(args.queue)
    up, down = link_models(args.delay, args.jitter, args.rate, args.loss, args.seed, args.rate_trace, reliable=tcp,
                           queue_bytes=queue if tcp else None)
    if args.webrtc:
        proxy = RtcLinkProxy(args.host, args.listen, to_host, to_port, up=up, down=down, max_queue_bytes=queue)
        units, conns = "datagrams", "signalling requests"
    else:
        proxy = LinkProxy(args.host, args.listen, to_host, to_port, up=up, down=down, max_queue_bytes=queue)
        units, conns = "messages", "connections"

    def report() -> None:
        s = proxy.stats
        print(f"link: stopped; {units} up {s.up.messages_forwarded} forwarded / {s.up.messages_dropped} dropped, "
              f"down {s.down.messages_forwarded} forwarded / {s.down.messages_dropped} dropped, "
              f"{s.connections_accepted} {conns}"
              + (f"; TCP segments lost (and sent again) up {up.stats.segments_lost} of {up.stats.segments_sent}, "
                 f"down {down.stats.segments_lost} of {down.stats.segments_sent}" if tcp else ""), flush=True)

    async def main() -> None:
        await proxy.start()
        rate = args.rate or "unlimited"
        if args.rate_trace:
            rate = f"{rate} up, {args.rate_trace} down"
        print(f"link: listening on {args.host}:{proxy.port} -> {to_host}:{to_port} ("
              f"{'webrtc: signalling and UDP, ' if args.webrtc else ''}delay {args.delay}, jitter "
              f"{args.jitter}, rate {rate}, loss {args.loss}"
              f"{' of TCP segments' if tcp else ' of whole messages' if not args.webrtc else ''}, queue {args.queue})",
              flush=True)
        await proxy.serve_forever()

    asyncio.run(_run_until_signal(main(), on_stop=report))
    return 0


# ---------------------------------------------------------------------------------------------- parsers

def video_option_help(key: str) -> str:
    """The help of `--crf` (key "crf") or `--chroma-qp-offset` ("chroma_qp_offset"), as `quadcast server` and
    `quadcast eval` take them, with each method's default read from `quadcast.protocol.methods.method_video`."""
    from quadcast.protocol.methods import METHODS, method_video
    what = {"crf": "x264 constant rate factor", "chroma_qp_offset": "x264 chroma-qp-offset, -12..12"}[key]
    methods_by_value: dict = {}
    for method in METHODS:
        methods_by_value.setdefault(method_video(method, None)[key], []).append(method)
    defaults = ", ".join(f"{'/'.join(names)} {value:g}" for value, names in methods_by_value.items())
    return f"{what} (default: each method's own: {defaults})"


def add_live_commands(sub) -> None:
    """Add ``server``, ``client`` and ``link`` to ``quadcast``'s subparsers."""
    from quadcast.cli import add_trace_placement
    from quadcast.protocol.admission import ServerLimits
    from quadcast.protocol.methods import METHODS
    lim = ServerLimits()

    p = sub.add_parser("server", help="live server: stream a method to clients over TCP or WebRTC")
    p.add_argument("--scene", default="builtin:courtyard")
    p.add_argument("--method", default="quasar", help=f"method(s) served, comma-separated: {', '.join(METHODS)}")
    p.add_argument("--host", default="127.0.0.1",
                   help="bind address (non-loopback needs --token, and TLS or --allow-plaintext-token)")
    p.add_argument("--port", type=int, required=True, help="TCP port (0: pick a free one and print it)")
    p.add_argument("--transport", default="tcp", choices=["tcp", "webrtc"],
                   help="webrtc: signalling over HTTP on --port, media and data over WebRTC")
    p.add_argument("--token", help="shared secret clients must send in Hello (WebRTC: also as the bearer token of "
                                   "POST /offer)")
    p.add_argument("--tls-cert", help="PEM certificate chain: serve TLS (TCP; WebRTC: HTTPS signalling)")
    p.add_argument("--tls-key", help="PEM private key of --tls-cert (default: in the --tls-cert file)")
    p.add_argument("--allow-plaintext-token", action="store_true",
                   help="accept a --token on a non-loopback --host without TLS (the token crosses in clear)")
    p.add_argument("--size", dest="max_size", default="1920x1080", help="largest client size served, WxH")
    p.add_argument("--hz", type=float, default=30.0, help="frame rate cap per session")
    p.add_argument("--viewcell", type=float, default=0.5, help="view-sphere radius, metres")
    p.add_argument("--reference-every", type=int, default=5, help="a reference frame at least every K frames")
    p.add_argument("--crf", type=float, help=video_option_help("crf"))
    p.add_argument("--chroma-qp-offset", type=int, help=video_option_help("chroma_qp_offset"))
    p.add_argument("--lead-ms", type=float, default=40.0,
                   help="the time from a frame's send to its first display: each frame is rendered for the pose "
                        "predicted this far beyond the measured encode time, plus half the frame interval (the "
                        "middle of the time it is shown)")
    p.add_argument("--no-predict", action="store_true", help="render the last received pose as is")
    p.add_argument("--adapt", action="store_true",
                   help="rate adaptation: each session's controller estimates the link from the client's receive "
                        "reports and picks each frame's operating point from the measured ladder, or the server's own "
                        "settings after 2 s of calm at the ladder's best point (quasar)")
    p.add_argument("--target-mbps", type=float, help="the rate controller's ceiling, Mbit/s (implies --adapt)")
    p.add_argument("--ladder", help="the operating points' ladder file (default: the measured one shipped)")
    p.add_argument("--point", help="every session's frames at this operating point (quasar): a ladder point's name "
                                   "or key=value,... as `quadcast eval --point` takes; foveated points centre on "
                                   "the gaze the client sends with its poses (`quadcast client --gaze`)")
    g = p.add_argument_group("limits")
    g.add_argument("--max-sessions", type=int, default=lim.max_sessions,
                   help="sessions at once; beyond, a client is told 'busy, retry after N s' (default %(default)s)")
    g.add_argument("--max-preauth", type=int, default=lim.max_preauth,
                   help="connections awaiting their handshake (TLS + Hello); others are closed at once "
                        "(default %(default)s)")
    g.add_argument("--max-per-ip", type=int, default=lim.max_per_ip,
                   help="connections from one address, any state (default %(default)s)")
    g.add_argument("--handshake-timeout", type=float, default=lim.handshake_timeout_s,
                   help="seconds from accept to an accepted Hello, TLS handshake included (default %(default)s)")
    g.add_argument("--idle-timeout", type=float, default=lim.idle_timeout_s,
                   help="end a session whose client sends no pose for this many seconds; other messages do not "
                        "count (default %(default)s)")
    g.add_argument("--retry-after", type=float, default=lim.retry_after_s,
                   help="seconds a busy server tells clients to wait (default %(default)s)")
    g.add_argument("--max-message-bytes", type=int, default=64 * 1024,
                   help="cap on a client message (default %(default)s)")
    g.add_argument("--max-peer-connections", type=int, default=8,
                   help="WebRTC peer connections at once, opening or open (default %(default)s)")
    p.add_argument("--stun", help="WebRTC: a STUN server URL (default: none; host candidates only)")
    p.add_argument("--pace", metavar="RATE",
                   help="WebRTC: send each session's RTP packets no faster than this, e.g. 40mbit (default: each "
                        "frame's packets at once, as aiortc does; a link with a shallow queue drops the burst)")
    p.add_argument("--unsent", metavar="SIZE", default="16k",
                   help="TCP: take each session's next frame once at most SIZE bytes of the last ones wait unsent in "
                        "the kernel (Linux), so frames wait in the session's queue, where stale ones are dropped, "
                        "not behind a slow link; 0 waits for all (default %(default)s)")
    p.add_argument("--worker", default="process", choices=["process", "thread"],
                   help="where each session renders and encodes: its own process (default), or a thread of the "
                        "server's process (stalls the event loop while it renders)")
    p.add_argument("--spare-workers", type=int, default=2,
                   help="worker processes kept booted for the next sessions (--worker process): all of them "
                        "while no session runs, one while sessions do")
    p.add_argument("--no-warm-up", action="store_true",
                   help="spare workers skip their warm-up (a few small frames of each method, so that llvmpipe "
                        "compiles the shaders before a session's first frames need them)")
    p.add_argument("-v", "--verbose", action="store_true", help="log sessions to stderr")
    p.set_defaults(func=cmd_server)

    p = sub.add_parser("client", help="live headless client: follow a trace against a server, record, score")
    p.add_argument("--connect", required=True, help="server (or link) HOST:PORT")
    p.add_argument("--trace", default="builtin:walk")
    p.add_argument("--scene", default="builtin:courtyard", help="scene the server renders (for ground truth)")
    p.add_argument("--method", default="quasar", choices=list(METHODS))
    p.add_argument("--size", default="960x540", help="WxH")
    p.add_argument("--fovy", type=float, default=60.0)
    p.add_argument("--duration", type=float, help="seconds (default: the rest of the trace)")
    p.add_argument("--start", type=float, default=0.0, help="trace time to start at, seconds")
    add_trace_placement(p, start=False)
    p.add_argument("--record-every", type=int, default=1, help="record (and score) every K-th displayed frame")
    p.add_argument("--gaze", help="a gaze trace ('t_ms x_deg y_deg' per line from the run's start, angles from the "
                                  "view axis) to send with the poses: a foveated server point centres on it, and "
                                  "FLIP over the central 20 degrees follows it (default: no gaze sent, the centre)")
    p.add_argument("--no-warm-up", action="store_true",
                   help="connect without first receiving and drawing made-up frames (so that llvmpipe compiles "
                        "the shaders before the first real frame needs them)")
    p.add_argument("--transport", default="tcp", choices=["tcp", "webrtc"])
    p.add_argument("--token", help="shared secret for the server")
    p.add_argument("--tls", action="store_true", help="connect with TLS, verifying the server against the system CAs")
    p.add_argument("--tls-ca", help="connect with TLS, trusting this PEM CA / self-signed certificate")
    p.add_argument("--insecure", action="store_true",
                   help="connect with TLS without verifying the server (encryption only)")
    p.add_argument("--stun", help="WebRTC: a STUN server URL (default: none)")
    p.add_argument("--retries", type=int, default=5,
                   help="connection attempts after a failure, a drop or a busy server, with exponential backoff "
                        "(0.5 s doubling to 2 s; at least the server's retry-after)")
    p.add_argument("--no-score", action="store_true", help="record only; skip the ground-truth scoring")
    p.add_argument("--stereo", action="store_true",
                   help="also show and record both eyes (the right one synthesized with YORO from the quad mesh) and "
                        "score the synthesized eye as `quadcast eval --stereo` does (quasar, quadstream)")
    p.add_argument("--label-latency", type=float, help="link latency to note in the summary, ms")
    p.add_argument("--label-jitter", type=float, help="link jitter to note in the summary, ms")
    p.add_argument("--label-loss", type=float, help="link loss to note in the summary, fraction")
    p.add_argument("--label-viewcell", type=float, help="server view-cell radius to note in the summary, m")
    p.add_argument("--out", required=True)
    p.add_argument("-v", "--verbose", action="store_true")
    p.set_defaults(func=cmd_client)

    p = sub.add_parser("link", help="netem-like proxy between a client and a server (TCP, or with --webrtc the "
                                    "WebRTC signalling and its UDP paths)")
    p.add_argument("--listen", type=int, required=True, help="port to listen on (0: a free one, printed)")
    p.add_argument("--host", default="127.0.0.1", help="listen address")
    p.add_argument("--public", action="store_true", help="allow a non-loopback --host")
    p.add_argument("--to", required=True, help="server HOST:PORT")
    p.add_argument("--delay", default="20ms", help="one-way delay, e.g. 20ms")
    p.add_argument("--jitter", default="10ms", help="uniform jitter, e.g. 10ms")
    p.add_argument("--rate", help="rate cap per direction, e.g. 200mbit")
    p.add_argument("--rate-trace", help="server -> client capacity over time instead of --rate: a Mahimahi trace "
                                        "(one line per 1500-byte delivery opportunity, ms; it repeats) or "
                                        "builtin:const-20|step-100-15-100|sawtooth-10-40")
    p.add_argument("--loss", default="0%",
                   help="loss per direction, e.g. 0.5%%: of TCP segments, which TCP sends again a round trip later "
                        "and halves its window for (its window is modelled, Reno's); of datagrams with --webrtc; of "
                        "whole messages with --drop-messages")
    p.add_argument("--drop-messages", action="store_true",
                   help="TCP link: drop whole messages (what a TCP connection never does; for trying the client's "
                        "recovery from a lost frame) instead of modelling TCP's retransmissions and window")
    p.add_argument("--queue", default="16m",
                   help="drop-tail queue per direction, bytes: what may wait for --rate (with --webrtc or "
                        "--drop-messages, also in the receiver's socket buffer) before a datagram, a message or a "
                        "TCP segment (sent again, the window halved) is dropped, e.g. 64k (default 16m)")
    p.add_argument("--webrtc", action="store_true",
                   help="for `--transport webrtc`: --to is the server's signalling port; the link answers the "
                        "client's POST /offer, puts its own UDP sockets in both descriptions and shapes every "
                        "datagram between the peers")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("-v", "--verbose", action="store_true")
    p.set_defaults(func=cmd_link)

