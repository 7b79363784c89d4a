"""The commands for quality under real head motion: --anchor/--start, `quadcast predict`'s table and
`quadcast bench quality` (on traces made here; tests never read the shared traces)."""
import json

import pytest

import quadcast.cli as quadcast
from quadcast.cli import bench
from quadcast.render.traces import builtin_trace


@pytest.fixture(scope="module")
def head_trace(tmp_path_factory):
    """A real-format head trace recorded somewhere else: the built-in walk, far from any scene."""
    path = tmp_path_factory.mktemp("traces") / "walk_elsewhere.txt"
    builtin_trace("walk").window(0.0, 3.0).anchored([50.0, 3.0, -40.0], 120.0).save(path)
    return path


def test_render_anchors_and_cuts_the_trace(tmp_path, head_trace):
    out = tmp_path / "r"
    assert quadcast.main(["-q", "render", "--trace", str(head_trace), "--anchor", "spawn", "--start", "1.0",
                          "--size", "64x36", "--frames", "3", "--every", "10", "--out", str(out)]) == 0
    assert len(list(out.glob("frame_*.png"))) == 3
    assert quadcast.main(["-q", "render", "--trace", str(head_trace), "--anchor", "0,1", "--out", str(out)]) == 2
    assert quadcast.main(["-q", "render", "--trace", str(head_trace), "--start", "9", "--out", str(out)]) == 2


def test_bad_anchor_is_a_named_error(capsys, head_trace, tmp_path):
    assert quadcast.main(["-q", "eval", "--trace", str(head_trace), "--anchor", "here", "--size", "64x36",
                          "--frames", "4", "--out", str(tmp_path)]) == 2
    assert "anchor 'here'" in capsys.readouterr().err


def test_predict_prints_a_table_with_and_without_prediction(capsys, tmp_path, head_trace):
    out = tmp_path / "p.json"
    assert quadcast.main(["predict", "--trace", str(head_trace), "--trace", "builtin:orbit", "--latency", "20,50",
                          "--jitter", "10,20", "--seeds", "2", "--json", str(out)]) == 0
    text = capsys.readouterr().out
    assert text.count("\n") == 5 and "walk_elsewhere" in text and "50±20" in text
    rows = json.loads(out.read_text())
    assert [(r["trace"].split("/")[-1], r["latency_ms"]) for r in rows] == [
        ("walk_elsewhere.txt", 20), ("walk_elsewhere.txt", 50), ("builtin:orbit", 20), ("builtin:orbit", 50)]
    for r in rows:
        assert r["predicted"]["position_cm"]["mean"] < 0.5 * r["none"]["position_cm"]["mean"]
        assert r["predicted"]["rotation_deg"]["mean"] <= r["none"]["rotation_deg"]["mean"]
        assert r["bound_violations"] == 0 and r["seeds"] == 2
    assert quadcast.main(["predict", "--latency", "20,50", "--jitter", "1,2,3"]) == 2


def test_bench_quality_rows_and_ratio(tmp_path, head_trace, capsys):
    rows = bench.bench_quality([str(head_trace)], scenes=("builtin:courtyard",), methods=("quasar", "meshwarp"),
                               latencies=((50.0, 20.0),), size=(96, 54), frames=12, every=4, seconds=2.0,
                               quiet=True)
    assert [r["method"] for r in rows] == ["quasar", "meshwarp"]
    quasar, meshwarp = rows
    for r in rows:
        assert r["scene"] == "builtin:courtyard" and r["trace"] == "walk_elsewhere" and r["frames"] > 0
        assert 0 <= r["holes"] <= r["holes_max"] <= 1 and r["mbps"] > 0 and r["flip"] > 0
    assert quasar["flip_vs_meshwarp"] == pytest.approx(quasar["flip"] / meshwarp["flip"])
    assert quasar["residual_to_reference_bytes"] is not None and meshwarp["residual_to_reference_bytes"] is None
    table = bench.format_quality_table(rows)
    assert table.count("\n") == 4 and "| quasar |" in table
    assert "quasar FLIP / MeshWarp's" in capsys.readouterr().out


def test_bench_quality_without_traces_skips_with_a_message(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(bench, "SHARED_TRACES", tmp_path / "absent")
    assert bench.bench_quality(None) == []
    assert "skip bench quality: no head traces" in capsys.readouterr().out
    assert quadcast.main(["bench", "quality", str(tmp_path / "nope.txt")]) == 2
    assert quadcast.main(["bench", "quality", "--methods", "teleport"]) == 2
    assert quadcast.main(["bench", "server", str(tmp_path / "x.txt")]) == 2


def test_live_client_follows_the_trace_from_the_spawn_point(head_trace, courtyard):
    from quadcast.client.app import ClientConfig, LiveClient
    from quadcast.methods import make_client
    client = LiveClient(ClientConfig("127.0.0.1", 1, trace=str(head_trace), anchor="spawn", start=0.5), make_client)
    assert client.pose_at(0.5).position == pytest.approx(courtyard.spawn.position, abs=1e-9)
    assert client.duration == pytest.approx(2.5)
    with pytest.raises(ValueError, match="anchor"):
        LiveClient(ClientConfig("127.0.0.1", 1, trace=str(head_trace), anchor="1,2"), make_client)


def test_bench_client_rows_keep_the_draw_apart_from_the_full_render(capsys):
    """`bench client --json`: the client's stage times (its own draw among them) and the full render they are
    judged against are separate figures, and the ratio is the one printed."""
    rows = bench.bench_client(["builtin:courtyard"], [(160, 90)], frames=2, quiet=True)
    (row,) = rows
    assert set(row["ms"]) == set(bench.CLIENT_STAGES) and all(v > 0 for k, v in row["ms"].items() if k != "quad_update")
    assert row["total_ms"] == pytest.approx(sum(row["ms"].values()))
    assert row["ratio_to_render"] == pytest.approx(row["total_ms"] / row["render_ms"])
    assert row["render_ms"] != row["ms"]["render"]
    assert f"ratio {row['ratio_to_render']:.2f}" in capsys.readouterr().out
