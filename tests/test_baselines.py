"""ATW and MeshWarp baselines (server.baselines / client.baselines): round trips, warps, bad payloads."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from scipy.spatial.transform import Rotation
from skimage.metrics import peak_signal_noise_ratio

from quadcast.client.baselines import ATWClient, MeshWarpClient
from quadcast.codec.nal import contains_idr
from quadcast.codec.decoder import AtlasDecoder, VideoError
from quadcast.protocol.depth import decode_depth, encode_depth
from quadcast.protocol.errors import ProtocolError
from quadcast.protocol.frame import Method, decode_frame_payload, encode_frame_payload
from quadcast.render.atlas_texture import AtlasTexture
from quadcast.render.camera import Camera, Pose
from quadcast.server.baselines import ATWServer, MeshWarpServer

W, H = 160, 90
T = 0.0
# South-west quarter of the courtyard, looking north-west past columns and slightly up: near and far geometry, sky.
POSE = Pose.from_euler([-4.0, 1.6, 4.0], 5.0, 30.0)


def yawed(pose: Pose, deg: float) -> Pose:
    return Pose(pose.position, (pose.rotation * Rotation.from_euler("y", deg, degrees=True)).as_quat())


def psnr(truth: np.ndarray, img: np.ndarray) -> float:
    return float(peak_signal_noise_ratio(truth, img, data_range=255))


@pytest.fixture(scope="module")
def truth(courtyard_renderer):
    cache = {}

    def render(pose: Pose) -> np.ndarray:
        key = (*pose.position.round(9), *pose.quat.round(9))
        if key not in cache:
            cache[key] = courtyard_renderer.render(Camera.perspective(pose, W, H, 60.0), T).color
        return cache[key]
    return render


@pytest.fixture(scope="module")
def atw(courtyard_renderer):
    server, client = ATWServer(courtyard_renderer, W, H), ATWClient(W, H, 60.0)
    payload = server.encode(POSE, T)
    client.receive(decode_frame_payload(encode_frame_payload(payload)))  # through the wire form
    yield server, client, payload
    server.close()
    client.close()


@pytest.fixture(scope="module")
def meshwarp(courtyard_renderer):
    server, client = MeshWarpServer(courtyard_renderer, W, H), MeshWarpClient(W, H, 60.0, server_fovy=60.0)
    payload = server.encode(POSE, T)
    client.receive(decode_frame_payload(encode_frame_payload(payload)))
    yield server, client, payload
    server.close()
    client.close()


def test_black_before_any_payload(ctx):
    for client in (ATWClient(W, H), MeshWarpClient(W, H)):
        img = client.render(POSE)
        assert img.shape == (H, W, 3) and img.dtype == np.uint8 and not img.any()
        assert client.needs_reference
        client.close()


def test_atw_round_trip(atw, truth):
    _, client, payload = atw
    assert payload.method == Method.ATW and payload.geometry == b""
    assert np.allclose(payload.position, POSE.position) and np.allclose(payload.quat, POSE.quat)
    img = client.render(POSE)
    assert img.shape == (H, W, 3) and img.dtype == np.uint8
    assert psnr(truth(POSE), img) >= 28.0
    # At the render pose the warp is the identity: the decoded frame itself, as the GPU converts it.
    atlas = AtlasTexture(client.ctx)
    atlas.write(AtlasDecoder(output="yuv420").decode(payload.video))
    decoded = atlas.read_rgb()
    atlas.release()
    assert np.abs(img.astype(int) - decoded).max() <= 1
    assert np.abs(img.astype(int) - AtlasDecoder().decode(payload.video)).mean() < 1.0   # and the CPU's, nearly
    assert not client.needs_reference


def test_meshwarp_round_trip(meshwarp, truth, courtyard_renderer):
    _, client, payload = meshwarp
    assert payload.method == Method.MESHWARP
    depth = decode_depth(payload.geometry)
    ref = courtyard_renderer.render(Camera.perspective(POSE, W, H, 60.0), T).depth
    assert depth.shape == (H, W)
    np.testing.assert_array_equal(np.isinf(depth), np.isinf(ref))
    assert np.isinf(ref).any() and np.isfinite(ref).any()
    assert psnr(truth(POSE), client.render(POSE)) >= 28.0


def test_server_stats_and_keyframes(courtyard_renderer):
    server = ATWServer(courtyard_renderer, W, H, keyframe_interval=3)
    payloads = [server.encode(POSE, T) for _ in range(4)]
    assert [p.frame_id for p in payloads] == [0, 1, 2, 3]
    # Self-contained exactly when the encoder made an IDR, which the access units confirm.
    assert [p.self_contained for p in payloads] == [True, False, False, True]
    assert [contains_idr(p.video) for p in payloads] == [True, False, False, True]
    server.request_reference()
    assert server.encode(POSE, T).self_contained
    for p in payloads:
        assert p.stats.ms["render"] > 0 and p.stats.ms["video"] > 0
        assert len(p.video) > 0 and p.geometry == b""
    server.close()
    mw = MeshWarpServer(courtyard_renderer, W, H)
    p = mw.encode(POSE, T)
    assert p.stats.ms["depth"] > 0 and len(p.geometry) > 0
    mw.close()
    with pytest.raises(ValueError, match="even"):
        ATWServer(courtyard_renderer, 161, 90)
    with pytest.raises(ValueError, match="keyframe_interval"):
        ATWServer(courtyard_renderer, W, H, keyframe_interval=0)


def test_atw_rotation_beats_stale_frame(atw, truth):
    _, client, _ = atw
    new = yawed(POSE, 5.0)
    stale = psnr(truth(new), truth(POSE))
    warped = psnr(truth(new), client.render(new))
    assert warped > stale + 3.0, (warped, stale)


def test_meshwarp_translation_beats_atw(atw, meshwarp, truth):
    new = POSE.offset_local([0.3, 0.0, 0.0])
    atw_psnr = psnr(truth(new), atw[1].render(new))
    mesh_psnr = psnr(truth(new), meshwarp[1].render(new))
    assert mesh_psnr > atw_psnr + 3.0, (mesh_psnr, atw_psnr)
    # ATW ignores translation entirely: it still shows the frame as rendered.
    assert np.array_equal(atw[1].render(new), atw[1].render(POSE))


def test_meshwarp_120_covers_larger_rotations(courtyard_renderer, meshwarp, truth):
    server = MeshWarpServer(courtyard_renderer, W, H, fovy=120.0)
    assert (server.width, server.height) == (2 * W, 2 * H)
    client = MeshWarpClient(W, H, 60.0, server_fovy=120.0)
    client.receive(server.encode(POSE, T))
    assert psnr(truth(POSE), client.render(POSE)) >= 20.0  # 120 degrees at 2x is softer than 60 at 1x
    new = yawed(POSE, 25.0).offset_local([0.1, 0.0, 0.0])
    wide = psnr(truth(new), client.render(new))
    narrow = psnr(truth(new), meshwarp[1].render(new))
    assert wide > narrow + 1.0, (wide, narrow)
    server.close()
    client.close()


def test_bad_payloads_rejected_last_state_kept(atw, meshwarp):
    new = yawed(POSE, 3.0)
    for (_, client, good), other in ((atw, Method.MESHWARP), (meshwarp, Method.ATW)):
        before = client.render(new)
        bad = [dataclasses.replace(good, method=other),
               dataclasses.replace(good, quat=np.zeros(4))]
        for payload in bad:
            with pytest.raises(ProtocolError):
                client.receive(payload)
        assert np.array_equal(client.render(new), before)
        with pytest.raises(ProtocolError):
            client.receive("not a payload")  # type: ignore[arg-type]
        with pytest.raises(VideoError):
            client.receive(dataclasses.replace(good, video=b"\x00\x00\x01\x65" + bytes(range(256)) * 4))
        assert client.needs_reference  # the decoder waits for an IDR now
        assert np.array_equal(client.render(new), before)
        # A non-IDR access unit while waiting for the IDR changes nothing.
        client.receive(dataclasses.replace(good, video=b"\x00\x00\x01\x41" + bytes(64)))
        assert np.array_equal(client.render(new), before)
        client.receive(good)  # an IDR: recovered
        assert not client.needs_reference
        assert np.array_equal(client.render(new), before)

    _, client, good = meshwarp
    before = client.render(new)
    for geometry in (b"", b"junk", good.geometry[:-5], encode_depth(np.ones((H // 2, W // 2), np.float32))):
        with pytest.raises(ProtocolError):
            client.receive(dataclasses.replace(good, geometry=geometry))
        assert np.array_equal(client.render(new), before)


def test_each_method_codes_its_video_with_its_own_settings(courtyard_renderer):
    """quasar's atlas is coded at its own CRF with its colour 6 quantizer steps finer and its reference frames at
    ipratio 2; the baselines keep x264's defaults (CRF 23, chroma offset 0, ipratio 1.4). A CRF or an offset asked
    for (`quadcast eval --crf`, `--chroma-qp-offset`) replaces the method's own; one asked for alone leaves the
    other."""
    from quadcast.methods import make_server
    from quadcast.protocol.methods import MethodConfig
    for name, crf, offset, ipratio in (("quasar", 20.0, -6, 2.0), ("quadstream", 23.0, 0, 1.4),
                                       ("meshwarp", 23.0, 0, 1.4), ("atw", 23.0, 0, 1.4)):
        for asked_crf, asked_offset in ((None, None), (30.0, None), (None, -3), (30.0, 2)):
            config = MethodConfig(width=W, height=H, crf=asked_crf, chroma_qp_offset=asked_offset)
            server = make_server(name, courtyard_renderer, config)
            video = server.encoder.settings
            expected = (asked_crf or crf, offset if asked_offset is None else asked_offset)
            assert (video.crf, video.chroma_qp_offset, video.ipratio) == expected + (ipratio,), name
            server.close()
