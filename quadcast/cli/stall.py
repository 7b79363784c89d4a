"""How long the live server's event loop stalls while a session renders: worker thread vs worker process.

Not a test (it measures wall-clock time). For each ``--worker`` kind it runs a :class:`quadcast.server.app.LiveServer` in
this process with a 10 ms asyncio ticker on the same event loop, connects one ``quadcast client`` (a separate
process) at ``--size`` for ``--duration`` seconds over ``--transport`` (tcp or webrtc), and reports the ticker's
largest gap (and its 99th percentile) while the session ran: the longest time the loop could not read a pose or send
a frame.

    .venv/bin/python -m quadcast.cli.stall --size 1920x1080 --duration 8
"""
from __future__ import annotations

import argparse
import asyncio
import tempfile
from pathlib import Path

import numpy as np

TICK_S = 0.010


async def measure(worker: str, size: str, duration: float, scene: str, trace: str, transport: str = "tcp") -> dict:
    """Run one session against an in-process server with ``worker`` over ``transport``; the ticker's gaps while it
    ran."""
    from quadcast.cli.demo import Child, quadcast_argv
    from quadcast.methods import make_server
    from quadcast.server.app import LiveServer, ServerConfig

    server = LiveServer(ServerConfig(scene=scene, port=0, worker=worker), make_server, transport=transport)
    await server.start()
    loop = asyncio.get_running_loop()
    gaps: list[float] = []
    stop = asyncio.Event()

    async def ticker() -> None:
        last = loop.time()
        while not stop.is_set():
            await asyncio.sleep(TICK_S)
            now = loop.time()
            if server.active > 0:
                gaps.append(now - last)
            last = now

    tick = asyncio.create_task(ticker())
    with tempfile.TemporaryDirectory() as tmp:
        client = Child("client", quadcast_argv("client", "--connect", f"127.0.0.1:{server.port}", "--size", size,
                                               "--scene", scene, "--trace", trace, "--duration", duration,
                                               "--transport", transport,
                                               "--no-score", "--out", Path(tmp) / "out"), Path(tmp) / "client.log")
        try:
            code = await loop.run_in_executor(None, client.wait, duration + 300)
        finally:
            client.stop()
    for _ in range(300):                     # let the session end (its counters join the server's) before closing
        if server.active == 0 and server.sessions_ended:
            break
        await asyncio.sleep(0.1)
    stop.set()
    await tick
    await server.close()
    g = np.asarray(gaps) * 1e3
    done = server.totals
    return {"worker": worker, "client_exit": code, "ticks": int(g.size),
            "max_gap_ms": float(g.max()) if g.size else float("nan"),
            "p99_gap_ms": float(np.percentile(g, 99)) if g.size else float("nan"),
            "frames_encoded": done.frames_encoded,
            "encode_ms": done.encode_s_total * 1e3 / done.frames_encoded if done.frames_encoded else float("nan")}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--size", default="1920x1080")
    ap.add_argument("--duration", type=float, default=8.0)
    ap.add_argument("--scene", default="builtin:courtyard")
    ap.add_argument("--trace", default="builtin:walk")
    ap.add_argument("--workers", default="thread,process")
    ap.add_argument("--transport", choices=("tcp", "webrtc"), default="tcp")
    args = ap.parse_args(argv)
    for worker in args.workers.split(","):
        r = asyncio.run(measure(worker, args.size, args.duration, args.scene, args.trace, args.transport))
        print(f"{r['worker']:>7} ({args.transport}): event-loop max gap {r['max_gap_ms']:.0f} ms, p99 "
              f"{r['p99_gap_ms']:.0f} ms "
              f"({TICK_S * 1e3:g} ms ticker, {r['ticks']} ticks during the session; {r['frames_encoded']} frames "
              f"encoded at {args.size}, mean {r['encode_ms']:.0f} ms; client exit {r['client_exit']})", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
