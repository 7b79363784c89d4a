"""The browser's side of the live server: the viewer page, its data and its WebSocket, on the server's own port.

:class:`quadcast.server.app.LiveServer` reads the first four bytes of every TCP connection: a binary-protocol
client starts with a u32 message length (at most ``max_message_bytes``, 64 KiB), an HTTP request with a method
name (``GET `` read as a length would be 542 MB), so :func:`starts_http` tells them apart and :func:`serve_web`
takes the HTTP ones. Behind TLS (when the server has it) the same holds inside the decrypted stream.

Routes (GET only; one request per connection, ``Connection: close``):

- ``/`` and the viewer's static files (``viewer/``: ``index.html``, ``js/*.js``, ``shaders/*.glsl`` with their
  ``#include`` lines resolved as for the Python client's shaders -- ``render/quad.glsl`` is the same file --, and
  the npm dependency ``node_modules/fzstd/esm``); nothing else on disk is reachable;
- ``/config.json``: what the page needs to say Hello (methods, largest size, whether a token is required);
- ``/trace/builtin:NAME``: a built-in trace as JSON (times, positions, xyzw quaternions), for ``?trace=``;
- ``/ws``: the WebSocket (:mod:`quadcast.transport.websocket`) -- then the connection is a session like any other
  (:meth:`LiveServer.serve_channel`, the session core, the same wire messages).

Requests are logged without their query string; the token never reaches the server in a URL (the page keeps it
in the fragment and sends it in Hello).
"""
from __future__ import annotations

import asyncio
import json
import logging
import urllib.parse
from pathlib import Path

from quadcast.protocol.messages import PROTOCOL_VERSION
from quadcast.transport.websocket import HttpRequestError, accept_websocket, read_http_request, send_http_response

__all__ = ["VIEWER_DIR", "starts_http", "serve_web", "static_file"]

log = logging.getLogger("quadcast.server.web")

VIEWER_DIR = Path(__file__).resolve().parent / "viewer"

_HTTP_STARTS = (b"GET ", b"HEAD", b"POST", b"PUT ", b"DELE", b"OPTI", b"PATC", b"CONN", b"TRAC")

CONTENT_TYPES = {
    ".html": "text/html; charset=utf-8",
    ".js": "text/javascript; charset=utf-8",
    ".mjs": "text/javascript; charset=utf-8",
    ".css": "text/css; charset=utf-8",
    ".glsl": "text/plain; charset=utf-8",
    ".png": "image/png",
}

# the only part of node_modules the page loads
_NPM_SERVED = ("node_modules/fzstd/esm/",)


def starts_http(first: bytes) -> bool:
    """Whether the first four bytes of a connection start an HTTP request (see the module docstring)."""
    return first[:4] in _HTTP_STARTS


def static_file(url_path: str) -> tuple[bytes, str] | None:
    """The body and content type of a viewer file for a (decoded) URL path, or None when there is none to serve."""
    rel = "index.html" if url_path in ("/", "/index.html") else url_path.lstrip("/")
    parts = rel.split("/")
    if not rel or "\\" in rel or any(not p or p.startswith(".") for p in parts):
        return None
    if parts[0] == "node_modules" and not rel.startswith(_NPM_SERVED):
        return None
    path = (VIEWER_DIR / rel).resolve()
    content_type = CONTENT_TYPES.get(path.suffix)
    if content_type is None or not path.is_relative_to(VIEWER_DIR) or not path.is_file():
        return None
    if path.suffix == ".glsl":
        from quadcast.render.gl import read_glsl
        return read_glsl(path).encode(), content_type
    return path.read_bytes(), content_type


def _trace_json(name: str) -> bytes:
    from quadcast.render.traces import resolve_trace
    if not name.startswith("builtin:"):            # never a path on the server's disk
        raise ValueError(f"only built-in traces are served (builtin:NAME), got {name!r}")
    trace = resolve_trace(name)
    return json.dumps({"name": trace.name, "times": trace.times.tolist(), "positions": trace.positions.tolist(),
                       "quats": trace.quats.tolist()}).encode()


def _start_pose(server) -> dict:
    """Where the page's desktop view starts: builtin:walk's first pose in the courtyard, a tour's elsewhere."""
    from quadcast.render.traces import resolve_trace, scene_tour
    cfg = server.config
    trace = (resolve_trace("builtin:walk") if cfg.scene.startswith("builtin:courtyard")
             else scene_tour(server.scene.bounds()))
    return {"position": trace.positions[0].tolist(), "quat": trace.quats[0].tolist()}


def _config_json(server) -> bytes:
    cfg = server.config
    return json.dumps({"version": PROTOCOL_VERSION, "methods": list(cfg.methods), "scene": cfg.scene,
                       "max_size": [cfg.max_width, cfg.max_height], "server_hz": cfg.server_hz,
                       "token_required": bool(cfg.token), "start": _start_pose(server)}).encode()


async def serve_web(server, reader: asyncio.StreamReader, writer: asyncio.StreamWriter, initial: bytes,
                    ticket=None) -> None:
    """Answer one HTTP request on an accepted connection (see the module docstring); never raises. `ticket` is the
    connection's admission (server/app.py), which a WebSocket session keeps."""
    cfg = server.config
    peername = writer.get_extra_info("peername")
    peer = f"{peername[0]}:{peername[1]}" if isinstance(peername, tuple) else str(peername)
    handed_over = False
    try:
        try:
            protocol, request = await asyncio.wait_for(
                read_http_request(reader, writer, initial, cfg.max_message_bytes), cfg.handshake_timeout)
        except HttpRequestError as exc:
            log.info("http %s: %s", peer, exc)
            return
        path = urllib.parse.unquote(urllib.parse.urlsplit(request.path).path)
        log.debug("http %s: %s %s", peer, request.method, path)

        async def answer(status: int, body: bytes, content_type: str = "text/plain; charset=utf-8") -> None:
            await send_http_response(protocol, writer, status, body, content_type)

        if request.method != "GET":
            await answer(405, f"{request.method}: only GET is served here\n".encode())
        elif path == "/ws":
            try:
                channel = await accept_websocket(protocol, request, reader, writer, cfg.max_message_bytes,
                                                 f"{peer} (websocket)")
            except HttpRequestError as exc:
                log.info("http %s: %s", peer, exc)
                return
            handed_over = True
            await server.serve_channel(channel, ticket)     # the session closes the channel
        elif path == "/config.json":
            await answer(200, _config_json(server), "application/json")
        elif path.startswith("/trace/"):
            try:
                await answer(200, _trace_json(path[len("/trace/"):]), "application/json")
            except ValueError as exc:               # TraceError is a ValueError
                await answer(404, f"{exc}\n".encode())
        else:
            found = static_file(path)
            if found is None:
                await answer(404, f"{path}: not found\n".encode())
            else:
                await answer(200, *found)
    except (ConnectionError, OSError, asyncio.TimeoutError):
        pass
    finally:
        if not handed_over:
            writer.close()
