"""What a connection flood costs a live server (issue 13's pre-auth figures), measured on a real ``quadcast server``
process: ``python -m quadcast.sim.flood [--connections 1000]``.

It starts a server (default limits, no spare worker), then opens ``--connections`` silent TCP connections from
one address (127.0.0.2), then as many again spread over 100 addresses (127.0.3.x), holding them all, and prints
the server process's open file descriptors and resident memory (from /proc) at each step, how many connections
the server refused at once, and the same after they are closed. Not a test: a figure for the README.
"""
from __future__ import annotations

import argparse
import asyncio
import re
import subprocess
import sys
import time
from pathlib import Path

__all__ = ["main"]


def _proc(pid: int) -> dict:
    status = Path(f"/proc/{pid}/status").read_text()
    kib = {k: int(v) for k, v in re.findall(r"^(VmRSS|VmHWM):\s+(\d+) kB", status, re.M)}
    return {"fds": len(list(Path(f"/proc/{pid}/fd").iterdir())), "rss_mib": kib["VmRSS"] / 1024,
            "peak_rss_mib": kib["VmHWM"] / 1024}


async def _flood(port: int, sources: list[str], n: int) -> tuple[list, int]:
    """Open ``n`` silent connections, round-robin over ``sources``; return them and how many the server closed
    (or refused) within a second."""
    conns = []
    for i in range(n):
        try:
            conns.append(await asyncio.open_connection("127.0.0.1", port, local_addr=(sources[i % len(sources)], 0)))
        except OSError:
            pass
    await asyncio.sleep(1.0)
    closed = 0
    for reader, _ in conns:
        try:
            data = await asyncio.wait_for(reader.read(65536), 0.01)
            closed += data == b"" or bool(data)       # EOF, or an ErrorMessage before the close
        except asyncio.TimeoutError:
            pass
        except OSError:
            closed += 1
    return conns, closed


def _line(step: str, s: dict, extra: str = "") -> str:
    return f"flood: {step:<44} fds {s['fds']:>5}  RSS {s['rss_mib']:7.1f} MiB  peak {s['peak_rss_mib']:7.1f} MiB{extra}"


async def _run(pid: int, port: int, n: int) -> None:
    print(_line("server idle", _proc(pid)), flush=True)
    one, closed1 = await _flood(port, ["127.0.0.2"], n)
    print(_line(f"{n} silent connections from one address", _proc(pid), f"  ({closed1} closed at once)"), flush=True)
    many, closed2 = await _flood(port, [f"127.0.3.{i}" for i in range(1, 101)], n)
    print(_line(f"+ {n} more from 100 addresses", _proc(pid), f"  ({closed2} closed at once)"), flush=True)
    await asyncio.sleep(11.0)          # past the handshake timeout (10 s): the held ones are closed too
    print(_line("11 s later (handshake timeout 10 s)", _proc(pid)), flush=True)
    for _, writer in one + many:
        writer.close()
    await asyncio.sleep(1.0)
    print(_line("all closed", _proc(pid)), flush=True)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m quadcast.sim.flood", description=__doc__.split("\n\n")[0])
    p.add_argument("--connections", type=int, default=1000)
    args = p.parse_args(argv)
    server = subprocess.Popen([sys.executable, "-m", "quadcast", "server", "--port", "0", "--spare-workers", "0"],
                              stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    try:
        deadline = time.monotonic() + 120
        port = None
        while port is None and time.monotonic() < deadline:
            line = server.stdout.readline()
            m = re.search(r"listening on [^:]+:(\d+)", line)
            port = int(m.group(1)) if m else None
        if port is None:
            print("flood: the server did not start", file=sys.stderr)
            return 1
        asyncio.run(_run(server.pid, port, args.connections))
    finally:
        server.terminate()
        server.wait(30)
    return 0


if __name__ == "__main__":
    sys.exit(main())
