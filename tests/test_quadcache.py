import numpy as np
import pytest

from quadcast.protocol.quads import OFFSETS_PER_QUAD, QuadSet
from quadcast.render.quadcache import QuadCache


def random_quads(rng, n, width, height, max_size_log2):
    flat = rng.random(n) < 0.5
    normal = rng.normal(size=(n, 3))
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    return QuadSet(x=rng.integers(0, width, n), y=rng.integers(0, height, n),
                   size_log2=rng.integers(0, max_size_log2 + 1, n), flattened=flat, alpha=np.zeros(n, bool),
                   normal=normal, depth=rng.uniform(0.5, 50.0, n),
                   offsets=rng.normal(scale=0.1, size=(int((~flat).sum()), OFFSETS_PER_QUAD)))


def loop_rasterize(index_map, quads, first_index):
    """The cache's rule written as the plain loop: 1-pixel quads by index, then the larger ones by index."""
    h, w = index_map.shape
    order = [i for i in range(len(quads)) if quads.size_log2[i] == 0] + \
            [i for i in range(len(quads)) if quads.size_log2[i] != 0]
    for i in order:
        s, x, y = 1 << int(quads.size_log2[i]), int(quads.x[i]), int(quads.y[i])
        index_map[y:min(y + s, h), x:min(x + s, w)] = first_index + i


@pytest.mark.parametrize("n, max_size_log2", [(3000, 0), (400, 3), (60, 6), (8, 10)])
def test_cache_index_map_follows_the_write_order_also_where_quads_overlap(n, max_size_log2):
    """Every path of the vectorized rasterizer (sorted few pixels, disjoint, overlapping) gives the loop's map."""
    rng = np.random.default_rng(n)
    w, h = 96, 54
    cache, reference = QuadCache(w, h), np.full((h, w), -1, np.int32)
    first = random_quads(rng, n, w, h, max_size_log2)
    cache.reset(first)
    loop_rasterize(reference, first, 0)
    np.testing.assert_array_equal(cache.index_map, reference)
    for k in (5, 40, 1, 90, 17, 3, 60):
        update = random_quads(rng, k, w, h, min(max_size_log2, 3))
        n_old = len(cache)
        loop_rasterize(reference, update, n_old)
        freed = cache.update(update)
        owned = np.bincount(reference[reference >= 0], minlength=n_old + k) > 0
        assert freed == int((~owned).sum())
        remap = np.cumsum(owned) - 1
        expected = np.where(reference >= 0, remap[np.maximum(reference, 0)], -1)
        np.testing.assert_array_equal(cache.index_map, expected)
        assert len(cache) == int(owned.sum())
        reference = expected.astype(np.int32)


def test_cache_of_disjoint_quads_covers_each_pixel_once():
    """A layer's quads tile the image: after a reset every pixel belongs to the quad that covers it."""
    w, h = 64, 32
    xs, ys = np.meshgrid(np.arange(0, w, 4), np.arange(0, h, 4))
    n = xs.size
    quads = QuadSet(x=xs.ravel(), y=ys.ravel(), size_log2=np.full(n, 2), flattened=np.ones(n, bool),
                    alpha=np.zeros(n, bool), normal=np.tile([0.0, 0.0, 1.0], (n, 1)), depth=np.ones(n),
                    offsets=np.zeros((0, OFFSETS_PER_QUAD)))
    cache = QuadCache(w, h)
    cache.reset(quads)
    expected = (np.arange(h)[:, None] // 4) * (w // 4) + np.arange(w)[None, :] // 4
    np.testing.assert_array_equal(cache.index_map, expected)


def quadtree_tiling(rng, width, height, max_size_log2=4):
    """Quads tiling a width x height image as a quadtree's leaves do: aligned squares of mixed sizes, those on the
    right and bottom edges reaching past the image."""
    quads = []

    def split(x, y, level):
        if x >= width or y >= height:
            return
        if level == 0 or rng.random() < 0.4:
            quads.append((x, y, level))
            return
        half = 1 << (level - 1)
        for dy in (0, half):
            for dx in (0, half):
                split(x + dx, y + dy, level - 1)

    top = 1 << max_size_log2
    for y in range(0, height, top):
        for x in range(0, width, top):
            split(x, y, max_size_log2)
    x, y, size_log2 = (np.array(c) for c in zip(*quads))
    perm = rng.permutation(len(x))
    n = len(x)
    return QuadSet(x=x[perm], y=y[perm], size_log2=size_log2[perm], flattened=np.ones(n, bool),
                   alpha=np.zeros(n, bool), normal=np.tile([0.0, 0.0, 1.0], (n, 1)), depth=np.ones(n),
                   offsets=np.zeros((0, OFFSETS_PER_QUAD)))


@pytest.mark.parametrize("overlap", [False, True])
def test_cache_reset_of_a_tiling_matches_the_loop(overlap, monkeypatch):
    """A reference frame's layer (a quadtree's leaves, clipped at the edges, in any order) takes the reset's path
    for disjoint quads; one quad written twice (a malformed layer) the ordered one. Both give the loop's map, and
    each quad's pixel count is what the map says."""
    rng = np.random.default_rng(7)
    w, h = 100, 45        # not multiples of the largest quad: quads along the right and bottom edges are clipped
    quads = quadtree_tiling(rng, w, h, max_size_log2=6)
    assert len(np.unique(quads.size_log2)) >= 5
    if overlap:
        k = int(np.argmax(quads.size_log2 == 2))
        extra = quads.select(np.arange(len(quads)) == k)
        extra = QuadSet(x=extra.x + 1, y=extra.y, size_log2=extra.size_log2, flattened=extra.flattened,
                        alpha=extra.alpha, normal=extra.normal, depth=extra.depth, offsets=extra.offsets)
        quads = QuadSet.concatenate([quads, extra])
    cache, reference = QuadCache(w, h), np.full((h, w), -1, np.int32)
    ordered = []
    rasterize = cache._rasterize
    monkeypatch.setattr(cache, "_rasterize", lambda *args: ordered.append(1) or rasterize(*args))
    cache.reset(quads)
    assert bool(ordered) == overlap
    loop_rasterize(reference, quads, 0)
    np.testing.assert_array_equal(cache.index_map, reference)
    assert (reference >= 0).all()
    np.testing.assert_array_equal(cache._owned_pixels, np.bincount(reference.ravel(), minlength=len(quads)))


def test_a_planned_update_changes_nothing_until_applied():
    """`plan_update` leaves the cache as it was (a client works it out while its video decodes, and drops it if
    the frame is bad); `apply` then gives what `update` gives; a plan for an older state is refused."""
    rng = np.random.default_rng(7)
    w, h = 96, 54
    planned, updated = QuadCache(w, h), QuadCache(w, h)
    first = random_quads(rng, 400, w, h, 3)
    planned.reset(first)
    updated.reset(first)
    for k in (40, 0, 90, 3):
        update = random_quads(rng, k, w, h, 3)
        before_map, before_quads, before_edit = planned.index_map.copy(), planned.quads, planned.edit
        plan = planned.plan_update(update)
        np.testing.assert_array_equal(planned.index_map, before_map)
        assert planned.quads is before_quads and planned.edit is before_edit
        assert planned.apply(plan) == updated.update(update)
        np.testing.assert_array_equal(planned.index_map, updated.index_map)
        assert len(planned) == len(updated)
        for field in ("x", "y", "size_log2", "depth"):
            np.testing.assert_array_equal(getattr(planned.quads, field), getattr(updated.quads, field))
    stale = planned.plan_update(random_quads(rng, 5, w, h, 2))
    planned.update(random_quads(rng, 5, w, h, 2))
    with pytest.raises(ValueError, match="older state"):
        planned.apply(stale)
    with pytest.raises(ValueError, match="another cache"):
        updated.apply(planned.plan_update(random_quads(rng, 5, w, h, 2)))
