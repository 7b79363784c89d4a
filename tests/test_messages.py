"""Tests for protocol.messages: the sans-I/O live wire protocol (typed messages + incremental decoder)."""

import struct

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from quadcast.protocol.errors import ProtocolError
from quadcast.protocol.frame import FramePayload, Method, FrameType
from quadcast.protocol.messages import (
    PROTOCOL_VERSION,
    Bye,
    ErrorCode,
    ErrorMessage,
    Frame,
    Hello,
    MessageDecoder,
    MessageSplitter,
    MessageType,
    PoseUpdate,
    ReceiveReport,
    ReferenceRequest,
    Welcome,
    decode_message_body,
    encode_message,
)

# -- strategies --------------------------------------------------------------

finite = st.floats(allow_nan=False, allow_infinity=False)
text = st.text(max_size=40)
u16 = st.integers(0, 0xFFFF)

hellos = st.builds(Hello, version=u16, method=text, width=st.integers(1, 2**32 - 1),
                   height=st.integers(1, 2**32 - 1),
                   fovy_deg=st.floats(0.0, 180.0, exclude_min=True, exclude_max=True), token=text)
welcomes = st.builds(Welcome, session_id=st.integers(0, 2**64 - 1),
                     server_hz=st.floats(0.0, 1e6, exclude_min=True))
quats = st.lists(st.floats(-1.0, 1.0), min_size=4, max_size=4).filter(lambda q: sum(v * v for v in q) > 1e-6)
poses = st.builds(PoseUpdate, seq=st.integers(0, 2**64 - 1), t_client=st.floats(-1e10, 1e10),
                  position=st.lists(st.floats(-1e5, 1e5), min_size=3, max_size=3), quat=quats,
                  gaze=st.none() | st.tuples(st.floats(-88.9, 88.9), st.floats(-88.9, 88.9)))
frames = st.builds(Frame, payload=st.binary(max_size=300))
refreqs = st.builds(ReferenceRequest, reason=text)
errors = st.builds(ErrorMessage, code=u16, text=text, retry_after_s=st.integers(0, 2**32 - 1).map(lambda ms: ms / 1e3))
reports = st.builds(ReceiveReport, entries=st.lists(st.tuples(st.integers(0, 2**32 - 1), st.integers(0, 2**32 - 1),
                                                               st.floats(-1e10, 1e10)), max_size=5).map(tuple))
messages = st.one_of(hellos, welcomes, poses, frames, refreqs, errors, st.just(Bye()), reports)


def _raw(mtype: int, body: bytes) -> bytes:
    return struct.pack("<IB", 1 + len(body), mtype) + body


# -- round trips -------------------------------------------------------------


@settings(max_examples=300, deadline=None)
@given(msg=messages)
def test_every_message_round_trips(msg):
    wire = encode_message(msg)
    assert struct.unpack_from("<I", wire)[0] == len(wire) - 4
    assert wire[4] == int({Hello: MessageType.HELLO, Welcome: MessageType.WELCOME,
                           PoseUpdate: MessageType.POSE_UPDATE, Frame: MessageType.FRAME,
                           ReferenceRequest: MessageType.REFERENCE_REQUEST, ErrorMessage: MessageType.ERROR,
                           Bye: MessageType.BYE, ReceiveReport: MessageType.RECEIVE_REPORT}[type(msg)])
    out = MessageDecoder().feed(wire)
    assert out == [msg]
    assert type(out[0]) is type(msg)


@settings(max_examples=100, deadline=None)
@given(msgs=st.lists(messages, max_size=8), cuts=st.lists(st.integers(0, 10_000), max_size=12))
def test_arbitrary_chunking_gives_the_same_messages(msgs, cuts):
    wire = b"".join(encode_message(m) for m in msgs)
    bounds = sorted({0, len(wire), *(c % (len(wire) + 1) for c in cuts)})
    dec = MessageDecoder()
    out = []
    for a, b in zip(bounds, bounds[1:]):
        out += dec.feed(wire[a:b])
    assert out == msgs
    assert dec.buffered == 0 and not dec.failed


def test_one_byte_at_a_time():
    msgs = [Hello(PROTOCOL_VERSION, "quasar", 320, 180, 60.0, token="sésame"), Welcome(42, 30.0),
            PoseUpdate(0, 0.5, [1, 2, 3], [0, 0, 0, 1]), Frame(b"\x00" * 1000), ReferenceRequest("lost"),
            ErrorMessage(ErrorCode.UNKNOWN_METHOD, "no such method"), Bye()]
    wire = b"".join(encode_message(m) for m in msgs)
    dec = MessageDecoder()
    out = []
    for i in range(len(wire)):
        got = dec.feed(wire[i:i + 1])
        out += got
        assert dec.buffered <= max(len(encode_message(m)) for m in msgs)
    assert out == msgs
    assert dec.feed(b"") == []


def test_frame_wraps_a_frame_payload():
    p = FramePayload(Method.QUASAR, 5, FrameType.RESIDUAL, 4, 1.25, np.array([1.0, 2.0, 3.0]),
                     np.array([0.0, 0.0, 0.0, 1.0]), video=b"h264" * 10, geometry=b"quads")
    (msg,) = MessageDecoder().feed(encode_message(Frame.from_payload(p)))
    q = msg.decode()
    assert (q.method, q.frame_id, q.frame_type, q.reference_id, q.t) == (Method.QUASAR, 5, FrameType.RESIDUAL, 4, 1.25)
    assert q.video == p.video and q.geometry == p.geometry
    np.testing.assert_array_equal(q.position, p.position)
    with pytest.raises(ProtocolError, match="truncated"):
        Frame(b"junk").decode()


def test_pose_update_from_pose_and_readonly_arrays():
    class P:
        position = np.array([1.0, 2.0, 3.0])
        quat = np.array([0.0, 0.0, 0.0, 2.0])

    m = PoseUpdate.from_pose(3, 0.1, P())
    assert m.quat.tolist() == [0.0, 0.0, 0.0, 2.0]  # sent as given, not normalized
    with pytest.raises(ValueError):
        m.position[0] = 5.0


def test_a_pose_without_a_gaze_is_the_body_it_always_was_and_one_with_it_adds_two_doubles():
    """Clients that do not track the eyes (the browser viewer) send the old body; the gaze is a trailing field."""
    plain = PoseUpdate(4, 1.25, [1, 2, 3], [0, 0, 0, 1])
    looked = PoseUpdate(4, 1.25, [1, 2, 3], [0, 0, 0, 1], (10.5, -3.0))
    assert encode_message(plain) == _raw(MessageType.POSE_UPDATE, struct.pack("<Qd3d4d", 4, 1.25, 1, 2, 3, 0, 0, 0, 1))
    assert encode_message(looked) == _raw(MessageType.POSE_UPDATE,
                                          struct.pack("<Qd3d4d2d", 4, 1.25, 1, 2, 3, 0, 0, 0, 1, 10.5, -3.0))
    assert MessageDecoder().feed(encode_message(looked) + encode_message(plain)) == [looked, plain]
    assert looked != plain and looked.gaze == (10.5, -3.0) and plain.gaze is None


def test_busy_error_carries_retry_after_and_plain_errors_stay_as_before():
    busy = ErrorMessage(ErrorCode.BUSY, "server busy", retry_after_s=2.5)
    wire = encode_message(busy)
    assert wire.endswith(struct.pack("<I", 2500))
    assert MessageDecoder().feed(wire) == [busy]
    plain = ErrorMessage(ErrorCode.PROTOCOL, "bad")          # no retry-after: the body of protocol version 1
    assert encode_message(plain) == _raw(MessageType.ERROR, struct.pack("<H", 1) + b"\x03\x00bad")
    assert MessageDecoder().feed(encode_message(plain))[0].retry_after_s == 0.0
    with pytest.raises(ValueError, match="retry_after_s"):
        ErrorMessage(ErrorCode.BUSY, "x", retry_after_s=-1.0)


@pytest.mark.parametrize("position, quat, t, match", [
    ([0, 0, 1e300], [0, 0, 0, 1], 0.0, "position"),
    ([0, 0, 0], [1e200, 1e200, 0, 1], 0.0, "quat"),
    ([0, 0, 0], [0, 0, 0, 1e-9], 0.0, "quat"),
    ([0, 0, 0], [0, 0, 0, 1], 1e300, "frame payload t"),
])
def test_frame_payload_poses_are_bounded_like_pose_updates(position, quat, t, match):
    from quadcast.protocol.frame import decode_frame_payload, encode_frame_payload
    p = FramePayload(Method.ATW, 1, FrameType.REFERENCE, 0, t, np.array(position, float), np.array(quat, float),
                     b"v", b"", True)
    with pytest.raises(ProtocolError, match=match):
        decode_frame_payload(encode_frame_payload(p))


# -- construction errors -----------------------------------------------------


@pytest.mark.parametrize("make, match", [
    (lambda: Hello(1, "quasar", 0, 180, 60.0), "Hello.width"),
    (lambda: Hello(1, "quasar", 320, 180, 180.0), "Hello.fovy_deg"),
    (lambda: Hello(70000, "quasar", 320, 180, 60.0), "Hello.version"),
    (lambda: Hello(1, "x" * 70000, 320, 180, 60.0), "Hello.method"),
    (lambda: Welcome(1, float("nan")), "Welcome.server_hz"),
    (lambda: PoseUpdate(0, 0.0, [0, 0, 0], [0, 0, 0, 0]), "PoseUpdate.quat"),
    (lambda: PoseUpdate(0, 0.0, [0, 0], [0, 0, 0, 1]), "PoseUpdate.position"),
    (lambda: PoseUpdate(0, 0.0, [0, 0, 0], [0, 0, 0, 1], (90.0, 0.0)), "PoseUpdate.gaze: .*89 degrees"),
    (lambda: PoseUpdate(0, 0.0, [0, 0, 0], [0, 0, 0, 1], (0.0,)), "PoseUpdate.gaze: expected 2"),
    (lambda: ErrorMessage(-1, "x"), "ErrorMessage.code"),
    (lambda: ReceiveReport(((1, -5, 0.0),)), r"ReceiveReport.entries\[0\].bytes"),
    (lambda: ReceiveReport(((1, 5, float("nan")),)), r"ReceiveReport.entries\[0\].t_arrive"),
    (lambda: ReceiveReport(((1, 5),)), r"ReceiveReport.entries\[0\]: expected"),
    (lambda: ReceiveReport(((1, 5, 0.0),) * 257), "at most 256"),
])
def test_invalid_fields_are_rejected_on_construction(make, match):
    with pytest.raises(ValueError, match=match):
        make()


def test_encode_rejects_non_messages():
    with pytest.raises(TypeError, match="dict"):
        encode_message({"seq": 1})


# -- malformed input ---------------------------------------------------------


def test_oversized_length_is_rejected_before_buffering():
    dec = MessageDecoder(max_message_bytes=1024)
    with pytest.raises(ProtocolError, match="1025 bytes exceeds the cap of 1024"):
        dec.feed(struct.pack("<IB", 1025, MessageType.FRAME) + b"\x00" * 500)
    assert dec.failed and dec.buffered == 0
    with pytest.raises(ProtocolError, match="already failed"):
        dec.feed(encode_message(Bye()))
    # exactly at the cap is fine
    ok = MessageDecoder(max_message_bytes=1024)
    assert ok.feed(encode_message(Frame(b"\x01" * 1023))) == [Frame(b"\x01" * 1023)]


def test_huge_declared_length_never_allocates():
    dec = MessageDecoder()  # 64 MiB cap
    with pytest.raises(ProtocolError, match="exceeds the cap"):
        dec.feed(b"\xff\xff\xff\xff")
    dec = MessageDecoder()
    dec.feed(struct.pack("<I", 60 * 2**20) + b"\x04" + b"\x00" * 100)  # legal length, partial body
    assert dec.buffered == 105


def test_zero_length_is_rejected():
    with pytest.raises(ProtocolError, match="length: 0"):
        MessageDecoder().feed(b"\x00\x00\x00\x00")


def test_unknown_type():
    dec = MessageDecoder()
    with pytest.raises(ProtocolError, match="unknown code 99"):
        dec.feed(_raw(99, b"abc"))
    assert dec.failed
    with pytest.raises(ProtocolError, match="unknown code 0"):
        decode_message_body(0, b"")


@pytest.mark.parametrize("mtype, body, match", [
    (MessageType.WELCOME, struct.pack("<Qd", 1, 30.0)[:-1], "Welcome: body truncated"),
    (MessageType.WELCOME, struct.pack("<Qd", 1, 30.0) + b"x", "Welcome: 1 unexpected trailing"),
    (MessageType.WELCOME, struct.pack("<Qd", 1, float("inf")), "Welcome.server_hz: expected a finite"),
    (MessageType.POSE_UPDATE, struct.pack("<Qd3d4d", 0, 0.0, 0, 0, 0, 0, 0, 0, 0), "PoseUpdate.quat: expected a non-zero"),
    # finite but absurd (issue 13): each is refused at decoding, naming the field
    (MessageType.POSE_UPDATE, struct.pack("<Qd3d4d", 0, 0.0, 0, 0, 0, 1e200, 1e200, 0, 1), "PoseUpdate.quat: .*norm"),
    (MessageType.POSE_UPDATE, struct.pack("<Qd3d4d", 0, 0.0, 0, 0, 0, 1e-5, 0, 0, 0), "PoseUpdate.quat: expected a non-zero"),
    (MessageType.POSE_UPDATE, struct.pack("<Qd3d4d", 0, 0.0, 1e300, 0, 0, 0, 0, 0, 1), "PoseUpdate.position: .*within"),
    (MessageType.POSE_UPDATE, struct.pack("<Qd3d4d", 0, 1e300, 0, 0, 0, 0, 0, 0, 1), "PoseUpdate.t_client: .*within"),
    (MessageType.ERROR, b"\x07\x00\x00\x00" + struct.pack("<I", 0), "retry_after_ms: 0"),
    (MessageType.POSE_UPDATE, struct.pack("<Qd3d4d", 0, 0.0, float("nan"), 0, 0, 0, 0, 0, 1), "PoseUpdate.position"),
    (MessageType.POSE_UPDATE, struct.pack("<Qd3d4d", 0, float("-inf"), 0, 0, 0, 0, 0, 0, 1), "PoseUpdate.t_client"),
    # the optional gaze: whole, finite and in front of the eye
    (MessageType.POSE_UPDATE, struct.pack("<Qd3d4dd", 0, 0.0, 0, 0, 0, 0, 0, 0, 1, 5.0), "PoseUpdate: body truncated "
     "reading gaze"),
    (MessageType.POSE_UPDATE, struct.pack("<Qd3d4d2d", 0, 0.0, 0, 0, 0, 0, 0, 0, 1, 5.0, float("nan")),
     "PoseUpdate.gaze: expected finite"),
    (MessageType.POSE_UPDATE, struct.pack("<Qd3d4d2d", 0, 0.0, 0, 0, 0, 0, 0, 0, 1, 5.0, -120.0),
     "PoseUpdate.gaze: .*89 degrees"),
    (MessageType.POSE_UPDATE, struct.pack("<Qd3d4d2d", 0, 0.0, 0, 0, 0, 0, 0, 0, 1, 5.0, 0.0) + b"x",
     "PoseUpdate: 1 unexpected trailing"),
    (MessageType.HELLO, struct.pack("<HIId", 1, 320, 180, 60.0) + b"\x02\x00\xff\xfe\x00\x00",
     "Hello.method: invalid utf-8"),
    (MessageType.HELLO, struct.pack("<HIId", 1, 320, 180, 60.0) + b"\x09\x00abc", "Hello: method says 9 bytes"),
    (MessageType.HELLO, struct.pack("<HIId", 1, 320, 180, 60.0) + b"\x00\x00", "Hello: body truncated reading token"),
    (MessageType.HELLO, struct.pack("<HIId", 1, 320, 180, float("nan")) + b"\x00\x00\x00\x00", "Hello.fovy_deg"),
    (MessageType.REFERENCE_REQUEST, b"\x01", "ReferenceRequest: body truncated"),
    (MessageType.ERROR, b"\x01\x00\x01\x00\x80", "ErrorMessage.text: invalid utf-8"),
    (MessageType.BYE, b"\x00", "Bye: 1 unexpected trailing"),
    (MessageType.RECEIVE_REPORT, struct.pack("<H", 2) + struct.pack("<IId", 1, 2, 0.5), "ReceiveReport: body truncated"),
    (MessageType.RECEIVE_REPORT, struct.pack("<H", 300), "ReceiveReport.count: 300 entries"),
    (MessageType.RECEIVE_REPORT, struct.pack("<H", 1) + struct.pack("<IId", 1, 2, float("inf")),
     r"ReceiveReport.entries\[0\].t_arrive"),
])
def test_malformed_bodies_name_the_problem(mtype, body, match):
    dec = MessageDecoder()
    with pytest.raises(ProtocolError, match=match):
        dec.feed(_raw(mtype, body))
    assert dec.failed


@settings(max_examples=500, deadline=None)
@given(data=st.binary(max_size=200), chunk=st.integers(1, 64))
def test_garbage_only_ever_raises_protocol_error(data, chunk):
    dec = MessageDecoder(max_message_bytes=4096)
    try:
        for i in range(0, len(data), chunk):
            dec.feed(data[i:i + chunk])
    except ProtocolError:
        assert dec.failed
    assert dec.buffered <= 4 + 4096


@settings(max_examples=300, deadline=None)
@given(mtype=st.integers(0, 255), body=st.binary(max_size=120))
def test_well_framed_garbage_bodies_only_raise_protocol_error(mtype, body):
    try:
        out = MessageDecoder().feed(_raw(mtype, body))
    except ProtocolError:
        return
    assert len(out) == 1 and encode_message(out[0]) == _raw(mtype, body)  # accepted => canonical


@settings(max_examples=200, deadline=None)
@given(msg=messages, pos=st.integers(0, 10_000), byte=st.integers(0, 255))
def test_corrupted_messages_only_raise_protocol_error(msg, pos, byte):
    wire = bytearray(encode_message(msg))
    wire[pos % len(wire)] = byte
    try:
        MessageDecoder(max_message_bytes=1 << 16).feed(bytes(wire))
    except ProtocolError:
        pass


def test_splitter_returns_whole_wire_messages():
    wire = [encode_message(m) for m in (Bye(), Frame(b"abc" * 100), Welcome(1, 2.0))]
    sp = MessageSplitter()
    blob = b"".join(wire)
    out = sp.feed(blob[:7]) + sp.feed(blob[7:300]) + sp.feed(blob[300:])
    assert out == wire
    # the splitter does not look at types or bodies
    assert MessageSplitter().feed(_raw(200, b"??")) == [_raw(200, b"??")]


def test_residual_to_reference_bytes_takes_any_iterable():
    from quadcast.protocol.frame import residual_to_reference_bytes
    frames = [(FrameType.REFERENCE, 100), (FrameType.RESIDUAL, 30), (FrameType.RESIDUAL, 50),
              (FrameType.REFERENCE, 300)]
    assert residual_to_reference_bytes(frames) == pytest.approx(40 / 200)
    assert residual_to_reference_bytes(iter(frames)) == pytest.approx(40 / 200)
    assert residual_to_reference_bytes(f for f in frames if f[0] == FrameType.REFERENCE) is None
