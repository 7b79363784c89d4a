"""quadcast: quad-based remote rendering for thin VR clients.

Installed, every part lives under this namespace; in the repository each has a folder of its own. Layers, lowest
first, each importing only those below it (``make test`` checks this with import-linter):

- ``quadcast.protocol``: the sans-I/O wire format, pose prediction and the session state machines;
- ``quadcast.codec``: H.264 encode/decode of the colour atlas and NAL helpers;
- ``quadcast.render``: headless GL, cameras and poses, scenes, traces, the deferred renderer, the layered quad mesh;
- ``quadcast.transport``: message channels over TCP and WebRTC;
- ``quadcast.server`` and ``quadcast.client``, side by side (neither imports the other);
- ``quadcast.methods``: every streaming method by name (its server half and its client half);
- ``quadcast.sim``: the link model, virtual-time replay, evaluation and reports;
- ``quadcast.cli``: the ``quadcast`` command and the benchmarks.
"""

__version__ = "0.1.0"
