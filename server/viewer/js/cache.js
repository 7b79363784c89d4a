// The cached reference frame (render/quadcache.py) in the page: the visible-layer quads of the last reference
// frame plus the updates of the residual frames since, as mesh rows (quads.js ROW_FLOATS floats each). A Quad
// Index Map (one int per reference pixel) says which cached quad covers each pixel; updates are rasterised over
// it (one-pixel quads first, then the larger ones in order, as the Python cache does) and quads left covering no
// pixel are freed.
import { ROW_FLOATS } from "./quads.js";

export class QuadCache {
  constructor(width, height) {
    this.width = width;
    this.height = height;
    this.rows = new Float32Array(0);
    this.count = 0;
    this.indexMap = new Int32Array(width * height).fill(-1);
    this.freedTotal = 0;
  }

  _rasterize(rows, count, first) {
    const { width, height, indexMap } = this;
    for (let pass = 0; pass < 2; pass++) {           // one-pixel quads, then the larger ones
      for (let i = 0; i < count; i++) {
        const r = i * ROW_FLOATS, x = rows[r], y = rows[r + 1], s = 1 << rows[r + 2];
        if ((s === 1) !== (pass === 0)) continue;
        const x1 = Math.min(x + s, width), y1 = Math.min(y + s, height);
        for (let yy = y; yy < y1; yy++) indexMap.fill(first + i, yy * width + x, yy * width + x1);
      }
    }
  }

  reset(rows, count) {
    this.rows = rows.slice(0, count * ROW_FLOATS);
    this.count = count;
    this.indexMap.fill(-1);
    this._rasterize(this.rows, count, 0);
  }

  // A residual frame's updated quads: append them, let them own their pixels, free quads left with none.
  update(rows, count) {
    if (count === 0) return 0;
    const nOld = this.count, total = nOld + count;
    this._rasterize(rows, count, nOld);
    const owned = new Uint8Array(total);
    const map = this.indexMap;
    for (let p = 0; p < map.length; p++) if (map[p] >= 0) owned[map[p]] = 1;
    const combined = new Float32Array(total * ROW_FLOATS);
    combined.set(this.rows.subarray(0, nOld * ROW_FLOATS));
    combined.set(rows.subarray(0, count * ROW_FLOATS), nOld * ROW_FLOATS);
    let kept = 0;
    const remap = new Int32Array(total);
    for (let i = 0; i < total; i++) {
      remap[i] = kept;
      if (owned[i]) {
        if (kept !== i) combined.copyWithin(kept * ROW_FLOATS, i * ROW_FLOATS, (i + 1) * ROW_FLOATS);
        kept++;
      }
    }
    const freed = total - kept;
    if (freed) for (let p = 0; p < map.length; p++) if (map[p] >= 0) map[p] = remap[map[p]];
    this.rows = freed ? combined.slice(0, kept * ROW_FLOATS) : combined;
    this.count = kept;
    this.freedTotal += freed;
    return freed;
  }
}
