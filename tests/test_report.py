"""Eval report writers: per-frame CSV, deterministic summary JSON, self-contained HTML, sweep table and plot."""
import base64
import csv
import io
import json
import re

import numpy as np
import pytest

from quadcast.sim.report import (
    FrameImages,
    flip_heatmap,
    format_value,
    plot_quality_vs_rate,
    round_float,
    summarize_records,
    write_comparison_table,
    write_frames_csv,
    write_report_html,
    write_summary_json,
)

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def _records(n: int = 12) -> list[dict]:
    rng = np.random.default_rng(3)
    out = []
    for i in range(n):
        bv, bg = int(rng.integers(20_000, 40_000)), int(rng.integers(5_000, 15_000))
        out.append(
            {
                "frame": i,
                "t": i / 30.0,
                "mbps": (bv + bg) * 8 * 30 / 1e6,
                "bytes_video": bv,
                "bytes_geometry": bg,
                "flip": float(rng.uniform(0.05, 0.2)),
                "ssim": float(rng.uniform(0.8, 0.95)),
                "psnr": np.float32(rng.uniform(25, 35)),  # numpy scalars are fine
                "pose_error_cm": float(rng.uniform(0, 2)),
                "pose_error_deg": float(rng.uniform(0, 1)),
                "latency_ms": 50.0 + i,
                "stage_ms": {"render": 4.0 + 0.1 * i, "encode": 2.5, "quads": 7.25},
            }
        )
    return out


def _summary() -> dict:
    return {
        "method": "quasar",
        "scene": "builtin:courtyard",
        "frames": 12,
        "flip_mean": 0.123456789123,
        "mbps_mean": np.float64(8.76543219),
        "size": (320, 180),
        "psnr": {"mean": 31.25, "max": float("inf")},
        "dropped": float("nan"),
    }


def _worst(h: int = 24, w: int = 32) -> list:
    rng = np.random.default_rng(5)
    gt = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
    shown = np.clip(gt.astype(int) + 30, 0, 255).astype(np.uint8)
    fmap = rng.uniform(0, 1, (h, w)).astype(np.float32)
    return [FrameImages(gt, shown, fmap, label="frame 7, FLIP 0.2"), (gt, shown, fmap[:, :, None])]


def test_csv_has_one_row_per_record(tmp_path):
    records = _records()
    path = write_frames_csv(tmp_path / "frames.csv", records)
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == len(records)
    header = list(rows[0].keys())
    assert header[:4] == ["frame", "t", "mbps", "bytes_video"]
    assert {"stage_ms.render", "stage_ms.encode", "stage_ms.quads"} <= set(header)
    assert rows[3]["frame"] == "3"
    assert float(rows[3]["t"]) == pytest.approx(0.1)
    assert float(rows[5]["stage_ms.render"]) == pytest.approx(4.5)
    assert float(rows[2]["psnr"]) == pytest.approx(float(records[2]["psnr"]), rel=1e-5)


def test_csv_missing_and_non_finite_values_are_empty(tmp_path):
    records = [{"frame": 0, "flip": 0.1}, {"frame": 1, "latency_ms": float("inf"), "note": "late"}]
    path = write_frames_csv(tmp_path / "f.csv", records)
    lines = path.read_text().splitlines()
    assert lines == ["frame,flip,latency_ms,note", "0,0.1,,", "1,,,late"]


def test_summary_json_is_deterministic(tmp_path):
    a = write_summary_json(tmp_path / "a.json", _summary())
    b = write_summary_json(tmp_path / "b.json", dict(reversed(list(_summary().items()))))
    assert a.read_bytes() == b.read_bytes()
    data = json.loads(a.read_text())
    assert list(data) == sorted(data)
    assert data["flip_mean"] == 0.123457  # 6 significant digits
    assert data["mbps_mean"] == 8.76543
    assert data["size"] == [320, 180]
    assert data["psnr"] == {"max": None, "mean": 31.25}
    assert data["dropped"] is None
    # Tiny float noise below the kept digits does not change the file.
    s = _summary()
    s["flip_mean"] += 1e-13
    c = write_summary_json(tmp_path / "c.json", s)
    assert c.read_bytes() == a.read_bytes()


def test_summary_json_rejects_unknown_types(tmp_path):
    with pytest.raises(TypeError, match="extra.obj"):
        write_summary_json(tmp_path / "x.json", {"extra": {"obj": object()}})
    with pytest.raises(TypeError, match="summary must be a dict"):
        write_summary_json(tmp_path / "x.json", [1, 2])


def _embedded_pngs(text: str) -> list[bytes]:
    return [base64.b64decode(m) for m in re.findall(r'src="data:image/png;base64,([A-Za-z0-9+/=]+)"', text)]


def test_html_report_is_self_contained(tmp_path):
    path = write_report_html(tmp_path / "report.html", _summary(), _records(), _worst())
    text = path.read_text()
    pngs = _embedded_pngs(text)
    # 4 plots (rate, quality, latency/pose error, stages) + 2 strips x 3 images.
    assert len(pngs) == 4 + 6
    assert all(p.startswith(PNG_MAGIC) for p in pngs)
    assert "http://" not in text and "https://" not in text
    assert 'src="' not in text.replace('src="data:image/png;base64,', "")
    for heading in ("Summary", "Per-frame statistics", "Over time", "Worst frames"):
        assert f"<h2>{heading}</h2>" in text
    assert "frame 7, FLIP 0.2" in text and "worst frame 2" in text


def test_html_report_contains_table_values(tmp_path):
    records = _records()
    path = write_report_html(tmp_path / "report.html", _summary(), records)
    text = path.read_text()
    assert "<td>flip_mean</td><td>0.1235</td>" in text
    assert "<td>mbps_mean</td><td>8.765</td>" in text
    assert "<td>psnr.mean</td><td>31.25</td>" in text
    assert "<td>method</td><td>quasar</td>" in text
    latency = summarize_records(records)["latency_ms"]
    assert latency["mean"] == pytest.approx(55.5) and latency["max"] == 61.0 and latency["n"] == 12
    assert f"<td>latency_ms</td><td>{format_value(latency['mean'])}</td>" in text
    assert len(_embedded_pngs(text)) == 4  # no worst frames given


def test_html_report_escapes_and_handles_sparse_records(tmp_path):
    path = write_report_html(tmp_path / "r.html", {"note": "<b>x</b>"}, [{"flip": 0.1}, {"flip": 0.2}], title="a<b")
    text = path.read_text()
    assert "&lt;b&gt;x&lt;/b&gt;" in text and "<title>a&lt;b</title>" in text
    assert len(_embedded_pngs(text)) == 1  # only the quality plot has data
    empty = write_report_html(tmp_path / "e.html", {}, [])
    assert "0 frames" in empty.read_text()


def test_html_report_rejects_bad_inputs(tmp_path):
    gt = np.zeros((8, 8, 3), np.uint8)
    with pytest.raises(ValueError, match=r"worst_frames\[0\].*share \(H, W\)"):
        write_report_html(tmp_path / "r.html", {}, [], [(gt, gt, np.zeros((4, 4)))])
    with pytest.raises(ValueError, match=r"worst_frames\[0\] ground truth must be sRGB uint8"):
        write_report_html(tmp_path / "r.html", {}, [], [(gt.astype(float), gt, np.zeros((8, 8)))])
    with pytest.raises(TypeError, match=r"worst_frames\[0\]"):
        write_report_html(tmp_path / "r.html", {}, [], [gt])
    with pytest.raises(TypeError, match=r"records\[1\] must be a dict"):
        write_report_html(tmp_path / "r.html", {}, [{"flip": 0.1}, 3])


def test_flip_heatmap():
    m = np.array([[0.0, 1.0], [0.5, 2.0]], np.float32)
    rgb = flip_heatmap(m)
    assert rgb.shape == (2, 2, 3) and rgb.dtype == np.uint8
    assert rgb[0, 0].sum() < 30 and rgb[0, 1].sum() > 600  # magma: black -> near white
    assert (rgb[1, 1] == rgb[0, 1]).all()  # clipped to 1
    with pytest.raises(ValueError, match="flip_map"):
        flip_heatmap(np.zeros((2, 2, 3)))


def _sweep() -> list[dict]:
    return [
        {"method": "quasar", "latency_ms": 50, "viewcell": 0.5, "mbps": 21.337, "flip": 0.0812, "ssim": 0.9312, "psnr": 31.456},
        {"method": "quasar", "latency_ms": 100, "viewcell": 0.5, "mbps": 35.1, "flip": 0.0923, "ssim": 0.92, "psnr": 30.0},
        {"method": "atw", "latency_ms": 50, "mbps": 9.87, "flip": 0.1504, "ssim": 0.8712, "psnr": 27.01},
        {"method": "a|b", "latency_ms": 50, "viewcell": "n/a", "mbps": 120.0, "flip": 0.05},
    ]


def test_comparison_table():
    table = write_comparison_table(_sweep())
    lines = table.strip().splitlines()
    assert len(lines) == 2 + 4
    assert lines[0] == "| Method | Latency (ms) | Viewcell (m) | Mbps | FLIP ↓ | SSIM ↑ | PSNR (dB) ↑ |"
    assert lines[2] == "| quasar | 50 | 0.5 | 21.34 | 0.0812 | 0.9312 | 31.46 |"
    assert lines[4] == "| atw | 50 | – | 9.87 | 0.1504 | 0.8712 | 27.01 |"
    assert lines[5] == "| a\\|b | 50 | n/a | 120.00 | 0.0500 | – | – |"
    with pytest.raises(ValueError, match=r"rows\[0\] has no 'method'"):
        write_comparison_table([{"mbps": 1.0}])


def test_quality_vs_rate_plot(tmp_path):
    path = plot_quality_vs_rate(_sweep(), tmp_path / "fig12.png")
    data = path.read_bytes()
    assert data.startswith(PNG_MAGIC) and len(data) > 5_000
    assert plot_quality_vs_rate(_sweep(), tmp_path / "again.png").read_bytes() == data
    with pytest.raises(ValueError, match=r"rows\[0\] \(x\): mbps must be > 0"):
        plot_quality_vs_rate([{"method": "x", "mbps": 0.0, "flip": 0.1}], tmp_path / "bad.png")
    with pytest.raises(ValueError, match=r"rows\[0\] \(x\): flip must be a finite number"):
        plot_quality_vs_rate([{"method": "x", "mbps": 1.0}], tmp_path / "bad.png")
    with pytest.raises(ValueError, match="at least one row"):
        plot_quality_vs_rate([], tmp_path / "bad.png")


def test_round_float():
    assert round_float(0.123456789) == 0.123457
    assert round_float(123456789.0) == 123457000.0
    assert round_float(0.0) == 0.0
    assert round_float(float("nan")) is None and round_float(float("-inf")) is None


def test_html_report_plots_holes_and_marks_them_in_the_strips(tmp_path):
    records = [{**r, "holes": 0.01 * i, "holes_smeared": 0.005 * i} for i, r in enumerate(_records())]
    gt, shown, fmap = _worst()[1]
    holes = np.zeros(shown.shape[:2], bool)
    holes[:, :8] = True
    frame = FrameImages(gt, shown, fmap[:, :, 0], "frame 3", holes)
    text = write_report_html(tmp_path / "report.html", _summary(), records, [frame]).read_text()
    assert "Holes over time" in text and "holes (magenta, 25.00%)" in text
    marked = _embedded_pngs(text)[-1]
    from PIL import Image
    image = np.asarray(Image.open(io.BytesIO(marked)))
    assert (image[:, :8] == [255, 0, 255]).all() and (image[:, 8:] == shown[:, 8:]).all()
    with pytest.raises(ValueError, match="holes"):
        write_report_html(tmp_path / "bad.html", _summary(), records, [FrameImages(gt, shown, fmap[:, :, 0], "x",
                                                                                   holes[:4])])
