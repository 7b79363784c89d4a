"""Sans-I/O protocol of quadcast (numpy, scipy and zstandard only; no sockets, no GL).

- :mod:`~quadcast.protocol.messages`: the live wire protocol's typed messages and incremental decoder;
- :mod:`~quadcast.protocol.frame`: one server frame (`FramePayload`) and its header;
- :mod:`~quadcast.protocol.quads`: 80-bit quads in columnar zstd blobs; :mod:`~quadcast.protocol.depth`: depth maps;
- :mod:`~quadcast.protocol.methods`: the streaming methods by name;
- :mod:`~quadcast.protocol.prediction`: head-pose prediction;
- :mod:`~quadcast.protocol.session`: the session state machines that the replay and the live system both drive.
"""
