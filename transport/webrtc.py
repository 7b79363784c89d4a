"""The live protocol over WebRTC (aiortc): :class:`WebRtcChannel` has the :class:`quadcast.transport.channel.Channel` interface.

What goes where, on one ``RTCPeerConnection``:

- the H.264 atlas (``FramePayload.video``) as the server's **video track**, sent *as encoded* (aiortc packetizes
  our access units; its own encoder is not used), RTP timestamp = 3000 x the frame's index on the track;
- the rest of each frame (header, pose, quads) in the split form of :func:`quadcast.protocol.frame.split_video`
  (track index and video length, then the frame without its video), joined on arrival with its access unit
  (:func:`quadcast.protocol.frame.join_video`) -- neither side parses or re-serializes the frame. It travels
  **inside its access unit** as an SEI user data NAL unit (:func:`access_unit_with_frame`), when the client takes
  the track's access units undecoded (below) and says so in its offer (``"frames": "in-access-unit"``) and the
  server's answer agrees: so the video track's NACKs and retransmissions carry the quads too, and a frame arrives
  whole or not at all. Otherwise it goes on the reliable ordered data channel ``frames`` as a ``Frame`` message, and
  the receiver pairs it with its picture. (aiortc's SCTP under loss falls seconds behind the track: the README's
  Known limitations has the figures);
- poses on the unordered, no-retransmit data channel ``poses`` (a lost pose is simply superseded);
- every other message (Hello, Welcome, ReferenceRequest, ErrorMessage, Bye) on the reliable channel ``control``.

Data channels carry the same length-prefixed wire messages as TCP, split into chunks of at most
:data:`CHUNK_BYTES` (SCTP message size limits), and are decoded by a capped
:class:`quadcast.protocol.messages.MessageDecoder` per channel.

Receiving video: aiortc has no API for a received track's encoded frames; its receiver reassembles each access
unit from the RTP packets (jitter buffer, NACKs) and queues it for a decoder thread. The client replaces that
jitter buffer with a :class:`~quadcast.transport.rtp_reassembly.FrameReassembly` (aiortc's holds 512 packets, less
than a 1920x1080 reference frame, and scans itself on every packet), and puts
:class:`AccessUnitTap` in place of that queue (:func:`tap_access_units`), so each access unit reaches the channel
with the NAL units the server's encoder wrote (behind the access unit delimiter below, and without the frame's SEI,
which the channel takes out) and the method client's own decoder, with its strict error detection, decodes it;
nothing is decoded twice or coded again. An access unit that carries no frame, or a malformed one, is a lost frame
(logged and counted in ``frames_unpaired``; the client asks for a reference as after any loss). Should a later
aiortc lay out its receiver otherwise, the tap is not installed (a warning is logged), frames go on the data
channel, and the channel falls back to what aiortc's decoder hands out: it **re-encodes** each decoded picture as a
standalone H.264 IDR (x264, crf :data:`REENCODE_CRF`; a generation of loss, and aiortc conceals damaged pictures
instead of refusing them). With frames on the data channel, pictures and frames wait to be paired (by RTP
timestamp) for at most :data:`PAIR_TIMEOUT_S` and :data:`MAX_PENDING_BYTES` each; a frame whose picture does not
come is dropped (the client then asks for a reference).
``bytes_in`` / ``bytes_out`` count data-channel bytes plus the bytes of the track's access units (no RTP/SRTP
overhead).

Signalling is one HTTP request: the client POSTs its offer (JSON ``{"sdp", "type"}``) to ``/offer`` on the
server's port and gets the answer back; :class:`WebRtcListener` is that endpoint (a tiny HTTP/1.1 server with
header and body caps, no dependency beyond aiortc). Its :class:`SignallingPolicy`: the request must carry the
server's token as ``Authorization: Bearer <token>`` when it has one (401 without, 403 when wrong) -- checked
before any peer connection exists; at most ``max_peer_connections`` peer connections live at once (503 with a
``Retry-After`` beyond); with ``ssl`` the endpoint is HTTPS; each request is a connection of the server's
:class:`quadcast.protocol.admission.Admission` (pre-auth and per-address caps). Peer connections on both sides use
no ICE server unless one is given (``stun``): aiortc's default is a public STUN server, so without this a server
would reach out to the internet for every offer.

What a peer can make the other side do is bounded where aiortc leaves it open (:mod:`quadcast.transport.peer_limits`):
the server's retransmissions on a client's NACKs, SCTP data held past the receive window (both sides), and data
channels beyond the three (the server closes them). The server's peer connections also let the event loop run while
they send a frame's packets (:func:`pace_rtp_sending`).
"""
from __future__ import annotations

import asyncio
import collections
import contextlib
import fractions
import hmac
import json
import logging
import math
import queue
import socket
import ssl as _ssl
import time
from dataclasses import dataclass
from typing import Awaitable, Callable

from quadcast.codec.nal import take_user_data, user_data_nal
from quadcast.protocol.admission import Admission, Refusal
from quadcast.protocol.errors import ProtocolError
from quadcast.protocol.frame import join_video, peek_frame_id, split_index, split_video
from quadcast.protocol.messages import Frame, Message, MessageDecoder, PoseUpdate, encode_message
from quadcast.transport.channel import Channel, ServerBusy
from quadcast.transport.peer_limits import is_power_of_two, limit_retransmissions, limit_sctp_receive
from quadcast.transport.rtp_reassembly import reassemble_in

__all__ = ["WebRtcChannel", "WebRtcListener", "SignallingPolicy", "open_webrtc_channel", "ice_configuration",
           "AccessUnitTap", "tap_access_units", "access_unit_with_frame", "frame_in_access_unit",
           "read_http_message", "http_response", "error_body", "parse_description", "CHUNK_BYTES", "REENCODE_CRF",
           "FRAMES_IN_BAND", "FRAMES_UUID", "SOCKET_BUFFER_BYTES", "ask_socket_buffers",
           "enlarge_socket_buffers", "keep_rtp_history", "pace_rtp_sending", "checked_pace",
           "SEND_YIELD_PACKETS"]

log = logging.getLogger("quadcast.webrtc")

CHUNK_BYTES = 16 * 1024
"""Largest data-channel message we send (SCTP implementations accept at least 64 KiB; stay well below)."""

REENCODE_CRF = 18.0
"""x264 quality of the receiver-side re-encode of decoded pictures, when the tap is not installed (see the module
docstring)."""

PAIR_TIMEOUT_S = 2.0
"""How long a received frame waits for its picture from the video track."""

MAX_PENDING = 32
"""Access units queued on the sending side's track."""

MAX_PENDING_BYTES = 64 << 20
"""Bytes of frames (without their video) and, apart, of pictures waiting to be paired; past this the oldest are
dropped. Nothing waits longer than :data:`PAIR_TIMEOUT_S` either. (Not a count: when the data channel lags behind
the video track, as SCTP does under loss, every picture would be dropped before its frame came.)"""

MAX_HTTP_HEADER = 16 * 1024
MAX_HTTP_BODY = 256 * 1024
VIDEO_CLOCK = 90_000
TICKS_PER_FRAME = 3000
ACCESS_UNIT_DELIMITER = b"\x00\x00\x00\x01\x09\xf0"
"""Sent with the *next* frame's timestamp right after each access unit: aiortc's jitter buffer releases a frame
only once a packet with a newer timestamp arrives, so this pushes every picture out at once (the delimiter then
starts the next access unit, where H.264 allows it)."""
CHANNELS = ("control", "poses", "frames")
FRAMES_IN_BAND = "in-access-unit"
"""The signalling field ``"frames"`` of a client that takes access units (offer) and of a server that agrees
(answer): each frame then travels inside its access unit, not on the ``frames`` data channel."""
FRAMES_UUID = b"quadcast/frame\x00\x01"
"""UUID of the SEI user data that carries a frame without its video inside the access unit (frames in band)."""


def _pc_classes():
    try:
        from aiortc import MediaStreamTrack, RTCPeerConnection, RTCSessionDescription
    except ImportError as exc:  # pragma: no cover - aiortc is a dependency
        raise RuntimeError(f"WebRTC transport needs aiortc: {exc}") from exc
    return MediaStreamTrack, RTCPeerConnection, RTCSessionDescription


def _aiortc_version() -> str:
    from importlib.metadata import PackageNotFoundError, version
    try:
        return version("aiortc")
    except PackageNotFoundError:  # pragma: no cover
        return "unknown version"


def ice_configuration(stun: str | None = None):
    """The peer connections' configuration: no ICE server (host candidates only) unless a ``stun`` URL is given
    (e.g. ``stun:stun.example.org:3478``). aiortc's own default would be a public STUN server."""
    from aiortc import RTCConfiguration, RTCIceServer
    if stun is not None and not stun.startswith(("stun:", "stuns:")):
        raise ValueError(f"--stun {stun!r}: expected a stun: URL, e.g. stun:stun.example.org:3478")
    return RTCConfiguration(iceServers=[RTCIceServer(urls=stun)] if stun else [])


def _atlas_track_class():
    MediaStreamTrack, _, _ = _pc_classes()

    class AtlasTrack(MediaStreamTrack):
        """A video track of pre-encoded H.264 access units (``av.Packet``), one per frame."""

        kind = "video"

        def __init__(self) -> None:
            super().__init__()
            self.queue: asyncio.Queue = asyncio.Queue(maxsize=MAX_PENDING)

        async def recv(self):
            packet = await self.queue.get()
            if packet is None:
                from aiortc.mediastreams import MediaStreamError
                self.stop()
                raise MediaStreamError("track ended")
            return packet

    return AtlasTrack


def access_unit_with_frame(rest: bytes, video: bytes) -> bytes:
    """The access unit ``video`` carrying its frame's ``rest`` (:func:`quadcast.protocol.frame.split_video`) in band:
    an SEI user data NAL unit (:data:`FRAMES_UUID`) in front of it."""
    return user_data_nal(FRAMES_UUID, rest) + video


def frame_in_access_unit(access_unit: bytes) -> bytes:
    """The encoded frame an access unit carries in band (:func:`access_unit_with_frame`): its rest joined with the
    access unit without the SEI. ProtocolError when it carries no frame or a malformed one."""
    rest, video = take_user_data(access_unit, FRAMES_UUID)
    if rest is None:
        raise ProtocolError(f"an access unit of {len(access_unit)} bytes carries no frame")
    return join_video(rest, video)


SOCKET_BUFFER_BYTES = 4 << 20
"""Receive and send buffer asked for each of a peer connection's UDP sockets (the kernel caps it at
net.core.rmem_max / wmem_max; Linux's default, about 208 kB, is less than one 960x540 reference frame's burst)."""


RTP_HISTORY_PACKETS = 4096
"""RTP packets aiortc's sender keeps for retransmission, and the span its receiver asks for lost ones in: a whole
frame of the largest the client's reassembly holds (:data:`~quadcast.transport.rtp_reassembly.REASSEMBLY_PACKETS`).
aiortc's own 128 is less than one 960x540 reference frame, so a NACK for one of a frame's first packets came back
after the whole frame was sent and found nothing to resend."""


def keep_rtp_history(packets: int = RTP_HISTORY_PACKETS) -> None:
    """Raise aiortc's ``RTP_HISTORY_SIZE`` (a module constant its sender and receiver read on every packet) to
    ``packets`` in this process: every aiortc peer connection of the process keeps that much. A process-wide
    setting, made by :class:`WebRtcListener` and :func:`open_webrtc_channel`; nothing happens if this aiortc has
    no such constant."""
    import aiortc.rtcrtpreceiver
    import aiortc.rtcrtpsender
    for module in (aiortc.rtcrtpsender, aiortc.rtcrtpreceiver):
        if isinstance(getattr(module, "RTP_HISTORY_SIZE", None), int) and module.RTP_HISTORY_SIZE < packets:
            module.RTP_HISTORY_SIZE = packets


def ask_socket_buffers(sock: socket.socket, nbytes: int = SOCKET_BUFFER_BYTES) -> bool:
    """Ask for ``nbytes`` of receive and send buffer on ``sock``; False if the kernel refused."""
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, nbytes)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, nbytes)
    except OSError:
        return False
    return True


def enlarge_socket_buffers(pc, nbytes: int = SOCKET_BUFFER_BYTES) -> int:
    """Ask for ``nbytes`` of receive and send buffer on the UDP sockets of ``pc``'s ICE transports, so a frame's
    burst of RTP packets is not dropped by the kernel before aiortc reads it (aiortc paces nothing and leaves the
    buffers at the system default). Best effort, through aioice's connection of each transport (not a public API):
    how many sockets were set."""
    done = set()
    for transceiver in pc.getTransceivers():
        for end in (transceiver.receiver, transceiver.sender):
            ice = getattr(getattr(end, "transport", None), "transport", None)
            for protocol in getattr(getattr(ice, "_connection", None), "_protocols", []):
                transport = getattr(protocol, "transport", None)
                sock = transport.get_extra_info("socket") if transport is not None else None
                if sock is not None and sock.fileno() not in done and ask_socket_buffers(sock, nbytes):
                    done.add(sock.fileno())
    return len(done)


SEND_YIELD_PACKETS = 32
"""RTP packets the server's peer connection sends before it lets the event loop run other work (see
:func:`pace_rtp_sending`)."""


def checked_pace(pace_mbit: float | None) -> float | None:
    """``pace_mbit`` if it is None (unpaced) or a rate > 0 Mbit/s; ValueError otherwise."""
    if pace_mbit is not None and not (math.isfinite(pace_mbit) and pace_mbit > 0):
        raise ValueError(f"pace must be a rate > 0 Mbit/s, got {pace_mbit!r}")
    return pace_mbit


def pace_rtp_sending(dtls_transport, every: int = SEND_YIELD_PACKETS, pace_mbit: float | None = None) -> bool:
    """Pace the RTP/RTCP packets ``dtls_transport`` (an aiortc ``RTCDtlsTransport``) sends: let the event loop run
    other work after every ``every`` of them, and with ``pace_mbit`` send them no faster than that. aiortc has no
    pacer: its sender encrypts and sends a frame's packets one after the other without yielding, so a 1920x1080
    frame of about 1,000 packets held the loop that serves every session for up to 58 ms, and a link's shallow queue
    drops the burst's tail. False (nothing changed) where the transport has no ``_send_rtp`` or is paced already."""
    send = getattr(dtls_transport, "_send_rtp", None)
    if not callable(send) or hasattr(send, "sent"):
        return False
    checked_pace(pace_mbit)
    sent = [0]
    free_at = [0.0]          # with a rate, when the pacer's virtual line is free again (loop time)

    async def send_paced(data: bytes) -> None:
        if pace_mbit is not None:
            now = asyncio.get_running_loop().time()
            start = max(now, free_at[0])
            free_at[0] = start + len(data) * 8 / (pace_mbit * 1e6)
            if start - now > 0.001:          # the loop's timers are about a millisecond fine
                await asyncio.sleep(start - now)
        await send(data)
        sent[0] += 1
        if sent[0] % every == 0:
            await asyncio.sleep(0)
    send_paced.sent = sent
    dtls_transport._send_rtp = send_paced
    return True


def _installed(done: bool, peer: str, otherwise: str) -> bool:
    """``done``, with a warning naming this aiortc's version and what ``otherwise`` happens when it is False (one of
    the stand-ins for aiortc's internals could not be put in place)."""
    if not done:
        log.warning("webrtc %s: this aiortc (%s) %s", peer, _aiortc_version(), otherwise)
    return done


class AccessUnitTap(queue.Queue):
    """Stands in for an aiortc ``RTCRtpReceiver``'s decoder queue: each reassembled H.264 access unit goes to
    ``deliver(rtp_timestamp, data)`` on the event loop, undecoded; anything else (another codec, the end marker
    ``None``) goes on to the receiver's decoder thread as before."""

    def __init__(self, deliver: Callable[[int, bytes], None]) -> None:
        super().__init__()
        self.deliver = deliver

    def put(self, item, block: bool = True, timeout: float | None = None) -> None:
        if item is not None:
            codec, encoded = item
            if codec.mimeType.lower() == "video/h264":
                self.deliver(int(encoded.timestamp), bytes(encoded.data))
                return
        super().put(item, block, timeout)


_DECODER_QUEUE = "_RTCRtpReceiver__decoder_queue"


def tap_access_units(receiver, deliver: Callable[[int, bytes], None]) -> bool:
    """Put an :class:`AccessUnitTap` in place of ``receiver``'s decoder queue, before the receiver starts. False
    (nothing changed) when this aiortc's receiver has no such queue or has started decoding."""
    current = getattr(receiver, _DECODER_QUEUE, None)
    thread = getattr(receiver, "_RTCRtpReceiver__decoder_thread", "missing")
    if type(current) is not queue.Queue or thread is not None or not current.empty():
        return False
    setattr(receiver, _DECODER_QUEUE, AccessUnitTap(deliver))
    return True


class WebRtcChannel(Channel):
    """The wire protocol over an open ``RTCPeerConnection`` (see the module docstring)."""

    def __init__(self, pc, channels: dict, max_message_bytes: int, video_out=None, peer: str = "webrtc") -> None:
        self.pc = pc
        self.dc = channels
        self.max_message_bytes = max_message_bytes
        self.video_out = video_out            # AtlasTrack on the sending side
        self.peer = peer
        self.bytes_in = self.bytes_out = 0
        self.closed = False
        self.frames_unpaired = 0
        self.frames_in_band = False           # each frame's rest travels in its access unit (both sides agreed)
        self._incoming: asyncio.Queue = asyncio.Queue()
        self._decoders = {name: MessageDecoder(max_message_bytes) for name in CHANNELS}
        self._video_index = 0
        self._meta: collections.OrderedDict[int, tuple[float, bytes]] = collections.OrderedDict()
        self._meta_bytes = 0
        # by track index, (arrival, bytes, picture): access units (bytes) from the tap, or aiortc's decoded pictures
        self._pictures: collections.OrderedDict[int, tuple[float, int, object]] = collections.OrderedDict()
        self._picture_bytes = 0
        self.access_units_tapped = False
        self._encoder = None
        self._video_task: asyncio.Task | None = None
        for name, dc in channels.items():
            dc.on("message", lambda data, name=name: self._on_message(name, data))
            dc.on("close", lambda: self._incoming.put_nowait(None))

        @pc.on("connectionstatechange")
        def _state() -> None:
            if pc.connectionState in ("failed", "closed"):
                self._incoming.put_nowait(None)

    # ---------------------------------------------------------------- receiving

    def tap_video(self, receiver) -> bool:
        """Take the access units of ``receiver``'s track undecoded (:func:`tap_access_units`; the client side,
        before the connection starts). False when aiortc's receiver does not allow it: then :meth:`attach_video`'s
        decoded pictures are re-encoded."""
        self.access_units_tapped = tap_access_units(receiver, self._on_access_unit)
        return self.access_units_tapped

    def attach_video(self, track) -> None:
        """Start consuming a remote video track (the client side; with the tap installed the track stays empty)."""
        self._video_task = asyncio.ensure_future(self._read_video(track))

    def _on_access_unit(self, rtp_timestamp: int, data: bytes) -> None:
        if self.closed:
            return
        if not self.frames_in_band:
            self._add_picture(rtp_timestamp // TICKS_PER_FRAME, data)
            return
        self.bytes_in += len(data)
        try:
            frame = Frame(frame_in_access_unit(data))
        except ProtocolError as exc:      # a damaged access unit is a lost frame: the client asks for a reference
            self.frames_unpaired += 1
            log.info("webrtc %s: access unit %d: %s; dropped", self.peer, rtp_timestamp // TICKS_PER_FRAME, exc)
            return
        self._incoming.put_nowait(frame)

    def _add_picture(self, index: int, picture) -> None:
        now = time.monotonic()
        self._take_picture(index)
        size = len(picture) if isinstance(picture, bytes) else picture.width * picture.height * 3 // 2
        self._pictures[index] = (now, size, picture)
        self._picture_bytes += size
        while self._pictures:
            t, _, _ = next(iter(self._pictures.values()))
            if self._picture_bytes <= MAX_PENDING_BYTES and now - t <= PAIR_TIMEOUT_S:
                break
            self._take_picture(next(iter(self._pictures)))
        self._pair()

    def _take_picture(self, index: int):
        entry = self._pictures.pop(index, None)
        if entry is None:
            return None
        self._picture_bytes -= entry[1]
        return entry[2]

    async def _read_video(self, track) -> None:
        try:
            while True:
                picture = await track.recv()
                self._add_picture(int(picture.pts or 0) // TICKS_PER_FRAME, picture)
        except Exception:  # noqa: BLE001 -- MediaStreamError when the track ends
            return

    def _on_message(self, name: str, data) -> None:
        if self.closed:
            return
        if isinstance(data, str):
            data = data.encode("utf-8")
        self.bytes_in += len(data)
        try:
            messages = self._decoders[name].feed(data)
        except ProtocolError as exc:
            self._incoming.put_nowait(exc)
            return
        for msg in messages:
            if name == "frames":
                if not isinstance(msg, Frame):
                    self._incoming.put_nowait(ProtocolError(f"frames channel: expected a Frame, got "
                                                            f"{type(msg).__name__}"))
                    return
                try:
                    index, video_bytes = split_index(msg.payload)
                except ProtocolError as exc:
                    self._incoming.put_nowait(exc)
                    return
                self.bytes_in += video_bytes
                self._take_meta(index)
                self._meta[index] = (time.monotonic(), msg.payload)
                self._meta_bytes += len(msg.payload)
                while self._meta_bytes > MAX_PENDING_BYTES:
                    self._take_meta(next(iter(self._meta)))
                    self.frames_unpaired += 1
                self._pair()
            else:
                self._incoming.put_nowait(msg)

    def _pair(self) -> None:
        """Hand out, in order, every frame whose picture has arrived; drop those waiting too long."""
        now = time.monotonic()
        while self._meta:
            index, (t_arrived, rest) = next(iter(self._meta.items()))
            picture = self._take_picture(index)
            if picture is None:
                newer_picture = any(i > index for i in self._pictures)
                if now - t_arrived > PAIR_TIMEOUT_S or (newer_picture and now - t_arrived > 0.2):
                    self._take_meta(index)
                    self.frames_unpaired += 1
                    log.info("webrtc %s: frame %d's picture never came; dropped", self.peer,
                             peek_frame_id(rest[8:]))
                    continue
                return
            self._take_meta(index)
            video = picture if isinstance(picture, bytes) else self._reencode(picture)
            self._incoming.put_nowait(Frame(join_video(rest, video)))

    def _take_meta(self, index: int) -> None:
        entry = self._meta.pop(index, None)
        if entry is not None:
            self._meta_bytes -= len(entry[1])

    def _reencode(self, picture) -> bytes:
        from quadcast.codec.encoder import AtlasEncoder, VideoSettings
        from quadcast.codec.picture import YuvPicture, frame_to_rgb
        # aiortc's decoder gives 4:2:0 pictures: coded again as they are, without a round trip through RGB
        image = YuvPicture.from_frame(picture) if picture.format.name == "yuv420p" else frame_to_rgb(picture)
        w, h = picture.width, picture.height
        if self._encoder is None or (self._encoder.width, self._encoder.height) != (w, h):
            if self._encoder is not None:
                self._encoder.close()
            self._encoder = AtlasEncoder(w, h, VideoSettings(crf=REENCODE_CRF))
        return self._encoder.encode(image, keyframe=True).data

    async def recv(self) -> Message | None:
        if self.closed and self._incoming.empty():
            return None
        item = await self._incoming.get()
        if isinstance(item, Exception):
            raise item
        return item

    # ---------------------------------------------------------------- sending

    def _send_bytes(self, name: str, data: bytes) -> None:
        if self.closed:
            raise ConnectionError(f"channel to {self.peer} is closed")
        dc = self.dc[name]
        if dc.readyState != "open":
            raise ConnectionError(f"data channel {name!r} to {self.peer} is {dc.readyState}")
        view = memoryview(data)
        for i in range(0, len(view), CHUNK_BYTES):
            dc.send(bytes(view[i:i + CHUNK_BYTES]))
        self.bytes_out += len(data)

    async def _drain(self, name: str, limit: int = 4 << 20) -> None:
        """Wait while a data channel has more than ``limit`` bytes buffered (backpressure, like drain())."""
        dc = self.dc[name]
        for _ in range(500):
            if dc.bufferedAmount <= limit or dc.readyState != "open":
                return
            await asyncio.sleep(0.01)

    async def send(self, msg: Message) -> None:
        if isinstance(msg, Frame):
            await self._send_frame(msg.payload)
            return
        name = "poses" if isinstance(msg, PoseUpdate) else "control"
        self._send_bytes(name, encode_message(msg))
        await self._drain(name)

    async def _send_frame(self, data: bytes) -> None:
        import av
        if self.video_out is None:
            raise RuntimeError("this WebRtcChannel has no outgoing video track (only the server sends frames)")
        index = self._video_index
        self._video_index += 1
        rest, video = split_video(data, index)
        if self.frames_in_band:
            video = access_unit_with_frame(rest, video)      # counted with the access unit, below
        else:
            self._send_bytes("frames", encode_message(Frame(rest)))
        for au, pts in ((video, index), (ACCESS_UNIT_DELIMITER, index + 1)):
            packet = av.Packet(au)
            packet.pts = pts * TICKS_PER_FRAME
            packet.time_base = fractions.Fraction(1, VIDEO_CLOCK)
            await self.video_out.queue.put(packet)
        self.bytes_out += len(video)
        await self._drain("frames")

    async def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        self._incoming.put_nowait(None)
        if self.video_out is not None:
            with contextlib.suppress(asyncio.QueueFull):
                self.video_out.queue.put_nowait(None)
        if self._video_task is not None:
            self._video_task.cancel()
        if self._encoder is not None:
            self._encoder.close()
        with contextlib.suppress(Exception):
            await asyncio.wait_for(self.pc.close(), 5.0)


# ------------------------------------------------------------------------------------------ signalling

async def read_http_message(reader: asyncio.StreamReader) -> tuple[str, dict, bytes]:
    """One HTTP/1.1 message: (start line, lower-case headers, body); ValueError on anything malformed/too big."""
    head = b""
    while b"\r\n\r\n" not in head:
        chunk = await reader.read(4096)
        if not chunk:
            raise ValueError("connection closed inside the HTTP header")
        head += chunk
        if len(head) > MAX_HTTP_HEADER:
            raise ValueError(f"HTTP header over {MAX_HTTP_HEADER} bytes")
    head, _, body = head.partition(b"\r\n\r\n")
    lines = head.decode("latin-1").split("\r\n")
    headers = {}
    for line in lines[1:]:
        key, sep, value = line.partition(":")
        if not sep:
            raise ValueError(f"bad HTTP header line {line[:80]!r}")
        headers[key.strip().lower()] = value.strip()
    try:
        length = int(headers.get("content-length", "0"))
    except ValueError:
        raise ValueError("bad Content-Length") from None
    if not 0 <= length <= MAX_HTTP_BODY:
        raise ValueError(f"HTTP body of {length} bytes (cap {MAX_HTTP_BODY})")
    while len(body) < length:
        chunk = await reader.read(length - len(body))
        if not chunk:
            raise ValueError("connection closed inside the HTTP body")
        body += chunk
    return lines[0], headers, body[:length]


def http_response(status: str, body: bytes, content_type: str = "application/json", extra: str = "") -> bytes:
    """An HTTP/1.1 response (``status`` as "200 OK"; ``extra``: more header lines, each ending in CRLF)."""
    return (f"HTTP/1.1 {status}\r\nContent-Type: {content_type}\r\nContent-Length: {len(body)}\r\n{extra}"
            f"Connection: close\r\n\r\n").encode() + body


def error_body(text: str) -> bytes:
    """The JSON body of a signalling error: ``{"error": text}``."""
    return json.dumps({"error": text}).encode()


def parse_description(body: bytes, expected_type: str) -> dict:
    """A signalling body (JSON ``{"type", "sdp"}``) of ``expected_type`` ("offer" or "answer"); ValueError if not."""
    try:
        desc = json.loads(body)
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"signalling body is not JSON: {exc}") from None
    if not isinstance(desc, dict) or desc.get("type") != expected_type or not isinstance(desc.get("sdp"), str):
        raise ValueError(f"signalling body must be {{\"type\": \"{expected_type}\", \"sdp\": \"...\"}}")
    return desc


@dataclass(frozen=True)
class SignallingPolicy:
    """Who may signal, and how much (see the module docstring). The defaults suit a loopback test server."""

    token: str = ""                         # required as "Authorization: Bearer <token>" when set
    ssl: _ssl.SSLContext | None = None       # HTTPS when given (a server context)
    admission: Admission | None = None       # the server's connection caps (None: none)
    max_peer_connections: int = 8            # peer connections alive at once (opening or open)
    retry_after_s: float = 5.0               # the Retry-After of a 503
    stun: str | None = None                  # ICE server (None: host candidates only)
    request_timeout: float = 10.0            # TLS handshake + request, per connection


class WebRtcListener:
    """The server side: an HTTP endpoint taking offers; each connection becomes a :class:`WebRtcChannel` handed to
    ``on_channel`` (a coroutine function, run as its own task)."""

    def __init__(self, host: str, port: int, on_channel: Callable[[WebRtcChannel], Awaitable[None]],
                 max_message_bytes: int = 64 * 1024, open_timeout: float = 15.0,
                 policy: SignallingPolicy | None = None, pace_mbit: float | None = None) -> None:
        self.host, self.requested_port = host, port
        self.pace_mbit = checked_pace(pace_mbit)    # each session's RTP sent no faster (None: as fast as it comes)
        self.on_channel = on_channel
        self.max_message_bytes = max_message_bytes
        self.open_timeout = open_timeout
        self.policy = policy or SignallingPolicy()
        ice_configuration(self.policy.stun)   # ValueError for a bad URL, now rather than per offer
        self._server: asyncio.AbstractServer | None = None
        self._tasks: set[asyncio.Task] = set()
        self._pcs: set = set()

    @property
    def port(self) -> int:
        return self._server.sockets[0].getsockname()[1]

    async def start(self) -> None:
        keep_rtp_history()
        self._server = await asyncio.start_server(self._on_http, self.host, self.requested_port)

    async def close(self) -> None:
        if self._server is not None:
            self._server.close()
        for t in list(self._tasks):
            t.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        for pc in list(self._pcs):
            with contextlib.suppress(Exception):
                await asyncio.wait_for(pc.close(), 3.0)

    def _busy(self, text: str) -> bytes:
        after = max(1, math.ceil(self.policy.retry_after_s))
        return http_response("503 Service Unavailable", error_body(text), extra=f"Retry-After: {after}\r\n")

    def _authorize(self, headers: dict) -> bytes | None:
        """The 401/403 response for a request without the right token, or None."""
        token = self.policy.token
        if not token:
            return None
        scheme, _, given = headers.get("authorization", "").partition(" ")
        if scheme.lower() != "bearer" or not given.strip():
            return http_response("401 Unauthorized", error_body("POST /offer needs Authorization: Bearer <token>"),
                                  extra='WWW-Authenticate: Bearer realm="quadcast"\r\n')
        if not hmac.compare_digest(given.strip().encode(), token.encode()):
            return http_response("403 Forbidden", error_body("wrong token"))
        return None

    async def _on_http(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        policy = self.policy
        peer = writer.get_extra_info("peername")
        peer = f"{peer[0]}:{peer[1]}" if isinstance(peer, tuple) else str(peer)
        ticket = policy.admission.open(peer.rpartition(":")[0] or peer) if policy.admission is not None else None
        if isinstance(ticket, Refusal):
            if policy.ssl is None:
                writer.write(self._busy(ticket.text))
            writer.close()
            return
        try:
            if policy.ssl is not None:
                try:
                    await writer.start_tls(policy.ssl, ssl_handshake_timeout=policy.request_timeout)  # not in wait_for (3.11)
                except (asyncio.TimeoutError, _ssl.SSLError, ConnectionError, OSError) as exc:
                    log.info("webrtc signalling from %s: TLS handshake failed: %s", peer, exc or "timed out")
                    return
            try:
                start, headers, body = await asyncio.wait_for(read_http_message(reader), policy.request_timeout)
                method, path, *_ = start.split(" ") + ["", ""]
                if method != "POST" or path != "/offer":
                    writer.write(http_response("404 Not Found", error_body("POST /offer only")))
                elif (denied := self._authorize(headers)) is not None:
                    log.info("webrtc signalling from %s: %s", peer, denied.split(b"\r\n", 1)[0].decode())
                    writer.write(denied)
                elif len(self._pcs) >= policy.max_peer_connections:
                    writer.write(self._busy(f"{policy.max_peer_connections} peer connections already"))
                else:
                    offer = parse_description(body, "offer")
                    answer = await self._accept(offer, peer)
                    writer.write(http_response("200 OK", json.dumps(answer).encode()))
            except (ValueError, asyncio.TimeoutError) as exc:
                writer.write(http_response("400 Bad Request", error_body(str(exc))))
            except Exception as exc:  # noqa: BLE001 -- a bad offer must not take the server down
                log.warning("webrtc signalling from %s failed: %s", peer, exc)
                writer.write(http_response("500 Internal Server Error", error_body(str(exc))))
            await writer.drain()
        except (ConnectionError, OSError):
            pass
        finally:
            writer.close()
            if ticket is not None:
                ticket.close()

    async def _accept(self, offer: dict, peer: str) -> dict:
        _, RTCPeerConnection, RTCSessionDescription = _pc_classes()
        pc = RTCPeerConnection(ice_configuration(self.policy.stun))
        self._pcs.add(pc)
        channels: dict = {}
        opened = asyncio.Event()

        refused = [0]

        @pc.on("datachannel")
        def _on_dc(dc) -> None:
            if dc.label in CHANNELS and dc.label not in channels:
                channels[dc.label] = dc
                if len(channels) == len(CHANNELS):
                    opened.set()
                return
            refused[0] += 1        # a label the protocol does not have, or one again: closed, not kept
            if is_power_of_two(refused[0]):
                log.info("webrtc %s: %d data channels closed (the last %r: not one of %s, or one again)", peer,
                         refused[0], dc.label[:40], ", ".join(CHANNELS))
            dc.close()

        track = _atlas_track_class()()
        in_band = offer.get("frames") == FRAMES_IN_BAND       # the client takes access units: frames go in them
        try:
            await pc.setRemoteDescription(RTCSessionDescription(sdp=offer["sdp"], type="offer"))
            sender = pc.addTrack(track)
            await pc.setLocalDescription(await pc.createAnswer())
        except Exception as exc:
            self._pcs.discard(pc)
            await pc.close()
            raise ValueError(f"bad offer: {exc}") from None

        _installed(pace_rtp_sending(sender.transport, pace_mbit=self.pace_mbit), peer,
                   "sends each frame without yielding")
        _installed(limit_retransmissions(sender), peer, "answers NACKs without a limit")
        _installed(limit_sctp_receive(pc.sctp), peer, "keeps SCTP data past its receive window")

        async def session() -> None:
            try:
                await asyncio.wait_for(opened.wait(), self.open_timeout)
            except asyncio.TimeoutError:
                log.warning("webrtc %s: data channels did not open within %g s", peer, self.open_timeout)
                self._pcs.discard(pc)
                await pc.close()
                return
            channel = WebRtcChannel(pc, channels, self.max_message_bytes, video_out=track, peer=peer)
            channel.frames_in_band = in_band
            enlarge_socket_buffers(pc)
            try:
                await self.on_channel(channel)
            finally:
                await channel.close()
                self._pcs.discard(pc)

        task = asyncio.create_task(session())
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)
        answer = {"sdp": pc.localDescription.sdp, "type": pc.localDescription.type}
        return {**answer, "frames": FRAMES_IN_BAND} if in_band else answer


async def _post_offer(host: str, port: int, offer: dict, timeout: float, token: str = "",
                      ssl: _ssl.SSLContext | None = None) -> dict:
    reader, writer = await asyncio.wait_for(
        asyncio.open_connection(host, port, ssl=ssl, server_hostname=host if ssl is not None else None), timeout)
    try:
        body = json.dumps(offer).encode()
        auth = f"Authorization: Bearer {token}\r\n" if token else ""
        writer.write((f"POST /offer HTTP/1.1\r\nHost: {host}:{port}\r\nContent-Type: application/json\r\n{auth}"
                      f"Content-Length: {len(body)}\r\nConnection: close\r\n\r\n").encode() + body)
        await writer.drain()
        start, headers, answer = await asyncio.wait_for(read_http_message(reader), timeout)
        status = (start.split(" ") + ["", ""])[1]
        said = f"signalling at {host}:{port} answered {start!r}: {answer[:200].decode('utf-8', 'replace')}"
        if status == "503":
            try:
                after = float(headers.get("retry-after", "5"))
            except ValueError:
                after = 5.0
            raise ServerBusy(said, after if math.isfinite(after) and after >= 0 else 5.0)
        if status in ("401", "403"):
            raise PermissionError(said)
        if status != "200":
            raise ConnectionError(said)
        return parse_description(answer, "answer")
    finally:
        writer.close()


async def open_webrtc_channel(host: str, port: int, max_message_bytes: int, timeout: float = 15.0,
                              token: str = "", ssl: _ssl.SSLContext | None = None,
                              stun: str | None = None) -> WebRtcChannel:
    """The client side: offer (receive-only video + the three data channels), signal over HTTP (HTTPS with a
    client ``ssl`` context; ``token`` as a bearer token), wait until the data channels are open. Raises
    :class:`ServerBusy` when the server has no room, PermissionError when it refuses the token."""
    _, RTCPeerConnection, RTCSessionDescription = _pc_classes()
    keep_rtp_history()
    pc = RTCPeerConnection(ice_configuration(stun))
    try:
        channels = {"control": pc.createDataChannel("control"),
                    "poses": pc.createDataChannel("poses", ordered=False, maxRetransmits=0),
                    "frames": pc.createDataChannel("frames")}
        peer = f"{host}:{port}"
        _installed(limit_sctp_receive(pc.sctp), peer, "keeps SCTP data past its receive window")
        from aiortc import RTCRtpReceiver
        video = pc.addTransceiver("video", direction="recvonly")
        h264 = [c for c in RTCRtpReceiver.getCapabilities("video").codecs if c.mimeType.lower() == "video/h264"]
        if not h264:
            raise RuntimeError("this aiortc build has no H.264 codec")
        video.setCodecPreferences(h264)   # the server sends our H.264 access units as they are
        channel = WebRtcChannel(pc, channels, max_message_bytes, peer=peer)
        _installed(reassemble_in(video.receiver), peer,
                   "keeps its own jitter buffer: frames of more than about 600 kB are lost")
        _installed(channel.tap_video(video.receiver), peer,
                   "does not let the channel take the video track's access units; its decoded pictures are "
                   "re-encoded (a generation of H.264 loss)")

        @pc.on("track")
        def _on_track(track) -> None:
            if track.kind == "video":
                channel.attach_video(track)

        await pc.setLocalDescription(await pc.createOffer())
        offer = {"sdp": pc.localDescription.sdp, "type": pc.localDescription.type}
        if channel.access_units_tapped:
            offer["frames"] = FRAMES_IN_BAND
        answer = await _post_offer(host, port, offer, timeout, token, ssl)
        channel.frames_in_band = channel.access_units_tapped and answer.get("frames") == FRAMES_IN_BAND
        await pc.setRemoteDescription(RTCSessionDescription(sdp=answer["sdp"], type="answer"))
        deadline = time.monotonic() + timeout
        while any(dc.readyState != "open" for dc in channels.values()):
            if time.monotonic() > deadline or pc.connectionState in ("failed", "closed"):
                raise ConnectionError(f"WebRTC to {host}:{port}: data channels did not open within {timeout:g} s "
                                      f"(connection {pc.connectionState})")
            await asyncio.sleep(0.02)
        if not enlarge_socket_buffers(pc):
            log.info("webrtc %s:%d: the UDP sockets' buffers were left at the system default", host, port)
        return channel
    except BaseException:
        with contextlib.suppress(Exception):
            await pc.close()
        raise
