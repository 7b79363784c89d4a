"""Every streaming method by name, so replay, evaluation and the live processes treat them the same.

`make_server(name, renderer, config)` and `make_client(name, config)` build the two halves of `quasar`,
`quadstream`, `meshwarp` (60° or, as `meshwarp120`, 120° at twice the resolution) and `atw`.
"""
from __future__ import annotations

from dataclasses import dataclass

import moderngl

from client.method import MethodClient
from render.renderer import DeferredRenderer
from server.method import MethodServer
from server.video import VideoSettings

METHODS = ("quasar", "quadstream", "meshwarp", "meshwarp120", "atw")


@dataclass(frozen=True)
class MethodConfig:
    width: int = 960
    height: int = 540
    fovy_deg: float = 60.0
    viewcell_radius: float = 0.5   # metres (QuadStream: half the side of its box viewcell)
    reference_every: int = 5
    layers: int = 4
    crf: float = 23.0


def _check(name: str) -> None:
    if name not in METHODS:
        raise ValueError(f"unknown method {name!r}; methods are {', '.join(METHODS)}")


def make_server(name: str, renderer: DeferredRenderer, config: MethodConfig) -> MethodServer:
    _check(name)
    video = VideoSettings(crf=config.crf)
    if name == "quasar":
        from server.quasar import QuasarServer, QuasarSettings
        return QuasarServer(renderer, QuasarSettings(width=config.width, height=config.height,
                                                     fovy_deg=config.fovy_deg, layers=config.layers,
                                                     viewcell_radius=config.viewcell_radius,
                                                     reference_every=config.reference_every, video=video))
    if name == "quadstream":
        from server.quadstream import QuadStreamServer, QuadStreamSettings
        return QuadStreamServer(renderer, QuadStreamSettings(width=config.width, height=config.height,
                                                             fovy_deg=config.fovy_deg,
                                                             viewcell_half=config.viewcell_radius, video=video))
    from server.baselines import ATWServer, MeshWarpServer
    if name == "atw":
        return ATWServer(renderer, config.width, config.height, config.fovy_deg, video=video)
    fovy = 120.0 if name == "meshwarp120" else config.fovy_deg
    return MeshWarpServer(renderer, config.width, config.height, fovy, video=video)


def make_client(name: str, config: MethodConfig, ctx: moderngl.Context | None = None) -> MethodClient:
    _check(name)
    if name in ("quasar", "quadstream"):
        from client.quasar import QuasarClient
        from protocol.frame import Method
        return QuasarClient(config.width, config.height, config.fovy_deg, ctx=ctx,
                            method=Method.QUASAR if name == "quasar" else Method.QUADSTREAM)
    from client.baselines import ATWClient, MeshWarpClient
    if name == "atw":
        return ATWClient(config.width, config.height, config.fovy_deg, ctx=ctx)
    server_fovy = 120.0 if name == "meshwarp120" else config.fovy_deg
    return MeshWarpClient(config.width, config.height, config.fovy_deg, server_fovy, ctx=ctx)
