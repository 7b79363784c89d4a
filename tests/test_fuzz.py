"""The short version of `make fuzz` (sim/fuzz.py): a few hundred inputs per target, none may raise anything but
its documented error or take over a second."""
import io

from quadcast.sim.fuzz import HANG_S, run_fuzz


def test_every_fuzz_target_only_raises_its_documented_error():
    out = io.StringIO()
    results = run_fuzz(300, out=out)
    text = out.getvalue()
    assert {r.target for r in results} == {"messages", "frame", "quads", "depth", "signalling", "access_unit",
                                                   "pose_path"}
    for r in results:
        assert r.inputs == 300, r.line()
        assert r.unexpected == 0, "\n".join(r.examples)
        assert r.hangs == 0 and r.slowest_s <= HANG_S
        assert 0 < r.accepted < r.inputs, r.line()      # both accepted and refused inputs were exercised
    assert "peak RSS" in text and "0 unexpected exceptions, 0 hangs" in text.splitlines()[-1]


def test_fuzz_counts_unexpected_exceptions(monkeypatch):
    import quadcast.sim.fuzz as fuzz
    _, check, expected = fuzz._targets()["depth"]

    def broken(data, chunk):
        raise KeyError("a decoder bug")
    monkeypatch.setitem(fuzz.TARGETS, "depth", (fuzz._seed_depth, broken, expected))
    r = fuzz.fuzz_target("depth", 20)
    assert r.unexpected == r.inputs == 20 and "KeyError" in r.examples[0]
