"""The cached reference frame (QUASAR §3.5, §3.6): the visible-layer quads of the last reference frame plus the
updates residual frames sent since, all in the reference camera's image space.

A Quad Index Map (one int32 per reference pixel) says which cached quad covers each pixel; updates are rasterised
over it, and a quad left covering no pixel is freed, so the cache never holds more quads than the image has
pixels. The client keeps one to display; the server keeps the same one to know what the client has.
Quads are axis-aligned pixel squares in this space, so rasterising them is array slicing.
"""
from __future__ import annotations

import numpy as np

from quadcast.protocol.quads import QuadSet


class QuadCache:
    def __init__(self, width: int, height: int):
        self.width, self.height = width, height
        self.quads = QuadSet.empty()
        self.index_map = np.full((height, width), -1, np.int32)
        self.freed_total = 0

    def __len__(self) -> int:
        return len(self.quads)

    @property
    def nbytes(self) -> int:
        q = self.quads
        return int(sum(getattr(q, f).nbytes for f in ("x", "y", "size_log2", "flattened", "alpha", "normal",
                                                      "depth", "offsets")) + self.index_map.nbytes)

    def _rasterize(self, quads: QuadSet, first_index: int) -> None:
        sizes = 1 << quads.size_log2.astype(np.int64)
        xs, ys = quads.x.astype(np.int64), quads.y.astype(np.int64)
        ones = sizes == 1
        ok = ones & (xs < self.width) & (ys < self.height)
        idx = np.arange(len(quads), dtype=np.int64) + first_index
        self.index_map[ys[ok], xs[ok]] = idx[ok]
        for i in np.flatnonzero(~ones):
            s = sizes[i]
            self.index_map[ys[i]:ys[i] + s, xs[i]:xs[i] + s] = idx[i]

    def reset(self, quads: QuadSet) -> None:
        """A reference frame: its visible-layer quads replace everything."""
        self.quads = quads
        self.index_map.fill(-1)
        self._rasterize(quads, 0)

    def update(self, quads: QuadSet) -> int:
        """A residual frame's updated quads: append them, let them own their pixels, free quads left with none.
        Returns how many quads were freed."""
        if len(quads) == 0:
            return 0
        n_old = len(self.quads)
        self._rasterize(quads, n_old)
        combined = QuadSet.concatenate([self.quads, quads])
        owned = np.bincount(self.index_map[self.index_map >= 0], minlength=len(combined)) > 0
        freed = int((~owned).sum())
        if freed:
            remap = np.cumsum(owned) - 1
            combined = combined.select(owned)
            valid = self.index_map >= 0
            self.index_map[valid] = remap[self.index_map[valid]]
        self.quads = combined
        self.freed_total += freed
        return freed
