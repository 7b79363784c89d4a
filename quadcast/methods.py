"""Every streaming method by name, so replay, evaluation and the live processes treat them the same.

`make_server(name, renderer, config)` and `make_client(name, config)` build the two halves of `quasar`,
`quadstream`, `meshwarp` (60° or, as `meshwarp120`, 120° at twice the resolution) and `atw`. This registry sits
above both halves: the live server and client are handed `make_server` / `make_client` by whoever starts them.
"""
from __future__ import annotations

import moderngl

from quadcast.client.method import MethodClient
from quadcast.protocol.frame import Method
from quadcast.codec.encoder import VideoSettings
from quadcast.render.renderer import DeferredRenderer
from quadcast.server.method import MethodServer
from quadcast.protocol.methods import METHODS, MethodConfig, check_method, method_video

def make_server(name: str, renderer: DeferredRenderer, config: MethodConfig) -> MethodServer:
    check_method(name)
    video = VideoSettings(**method_video(name, config.crf, config.chroma_qp_offset))
    if name == "quasar":
        from quadcast.server.quasar import QuasarServer, QuasarSettings
        return QuasarServer(renderer, QuasarSettings(width=config.width, height=config.height,
                                                     fovy_deg=config.fovy_deg, layers=config.layers,
                                                     viewcell_radius=config.viewcell_radius,
                                                     reference_every=config.reference_every, video=video))
    if name == "quadstream":
        from quadcast.server.quadstream import QuadStreamServer, QuadStreamSettings
        return QuadStreamServer(renderer, QuadStreamSettings(width=config.width, height=config.height,
                                                             fovy_deg=config.fovy_deg,
                                                             viewcell_half=config.viewcell_radius, video=video))
    from quadcast.server.baselines import ATWServer, MeshWarpServer
    if name == "atw":
        return ATWServer(renderer, config.width, config.height, config.fovy_deg, video=video)
    fovy = 120.0 if name == "meshwarp120" else config.fovy_deg
    return MeshWarpServer(renderer, config.width, config.height, fovy, video=video)


def make_client(name: str, config: MethodConfig, ctx: moderngl.Context | None = None) -> MethodClient:
    check_method(name)
    if name in ("quasar", "quadstream"):
        from quadcast.client.quasar import QuasarClient
        return QuasarClient(config.width, config.height, config.fovy_deg, ctx=ctx,
                            method=Method.QUASAR if name == "quasar" else Method.QUADSTREAM)
    from quadcast.client.baselines import ATWClient, MeshWarpClient
    if name == "atw":
        return ATWClient(config.width, config.height, config.fovy_deg, ctx=ctx)
    server_fovy = 120.0 if name == "meshwarp120" else config.fovy_deg
    return MeshWarpClient(config.width, config.height, config.fovy_deg, server_fovy, ctx=ctx)


__all__ = ["METHODS", "MethodConfig", "make_server", "make_client"]
