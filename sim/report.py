"""Writers for evaluation results: per-frame CSV, summary JSON, a self-contained HTML report, sweep tables and plots.

**Per-frame records** are plain dicts, one per displayed frame.  Any keys are
allowed; nested dicts are flattened with dots (``{"stage_ms": {"render": 3.1}}``
becomes the column ``stage_ms.render``).  The report knows these keys and plots
them when present (see :data:`CORE_COLUMNS`):

=====================  ====================================================
``frame``              frame index
``t``                  scene / display time, seconds (x axis of the plots)
``mbps``               downlink data rate for this frame, Mbit/s
``bytes_video``        encoded colour (H.264 atlas) bytes
``bytes_geometry``     encoded geometry (quad blob) bytes
``flip`` ``ssim``      image quality vs ground truth (:mod:`quadcast.sim.metrics`)
``psnr``               dB
``holes``              fraction of the display the client left without content
                       (nothing drawn or only smeared edge pixels), 0..1;
                       ``holes_empty`` / ``holes_smeared`` split it;
                       ``holes_interior``: the part not touching the border
``pose_error_cm``      distance between rendered and displayed pose, cm
``pose_error_deg``     angle between rendered and displayed pose, degrees
``latency_ms``         motion-to-photon (pose sent -> frame displayed), ms
``stage_ms``           dict of milliseconds per pipeline stage (e.g.
                       ``FramePayload.stats``), flattened to ``stage_ms.NAME``
=====================  ====================================================

**Determinism.**  Floats are rounded to :data:`FLOAT_DIGITS` significant
digits in the CSV and JSON, JSON keys are sorted, and non-finite floats
become ``null`` (JSON) or an empty cell (CSV), so the same data always gives
byte-identical files.

**Sweeps.**  :func:`write_comparison_table` and :func:`plot_quality_vs_rate`
take rows (dicts) with keys ``method``, ``latency_ms``, ``viewcell``,
``mbps``, ``flip``, ``ssim``, ``psnr`` -- one row per method x setting, like
QUASAR's Table 4 and Fig. 12.

Plots use matplotlib's ``Figure`` with the Agg canvas directly (no pyplot
global state, no display needed).
"""

from __future__ import annotations

import base64
import csv
import html
import io
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable, Mapping, Sequence

import numpy as np

__all__ = [
    "FLOAT_DIGITS",
    "CORE_COLUMNS",
    "STAGE_PREFIX",
    "COMPARISON_COLUMNS",
    "FrameImages",
    "flatten_record",
    "round_float",
    "format_value",
    "summarize_records",
    "write_frames_csv",
    "write_summary_json",
    "write_report_html",
    "write_comparison_table",
    "plot_quality_vs_rate",
    "flip_heatmap",
]

FLOAT_DIGITS = 6
"""Significant digits kept for floats in the CSV and JSON files."""

CORE_COLUMNS = (
    "frame",
    "t",
    "mbps",
    "bytes_video",
    "bytes_geometry",
    "flip",
    "ssim",
    "psnr",
    "holes",
    "pose_error_cm",
    "pose_error_deg",
    "latency_ms",
)
"""Per-frame columns the report knows, in CSV order; other columns follow, sorted by name."""

STAGE_PREFIX = "stage_ms."
"""Flattened columns starting with this are per-stage milliseconds (from ``record["stage_ms"]``)."""

COMPARISON_COLUMNS = (
    ("method", "Method"),
    ("latency_ms", "Latency (ms)"),
    ("viewcell", "Viewcell (m)"),
    ("mbps", "Mbps"),
    ("flip", "FLIP ↓"),
    ("ssim", "SSIM ↑"),
    ("psnr", "PSNR (dB) ↑"),
)
"""(row key, markdown header) of :func:`write_comparison_table`, in order."""

_COMPARISON_FORMATS = {"latency_ms": "{:g}", "mbps": "{:.2f}", "flip": "{:.4f}", "ssim": "{:.4f}", "psnr": "{:.2f}"}


@dataclass(frozen=True)
class FrameImages:
    """One frame shown in the report's worst-frames strip.

    ``gt`` and ``displayed`` are sRGB uint8 ``(H, W, 3)``; ``flip_map`` is the
    FLIP error, float ``(H, W)`` in ``[0, 1]`` (shown with the magma colour
    map) or an already coloured uint8 ``(H, W, 3)`` image.  ``label`` is the
    caption (e.g. ``"frame 42, t = 1.40 s, FLIP 0.21"``).  ``holes``, when
    given, is the client's (H, W) bool hole mask, shown as a fourth image
    (the displayed frame with its holes in magenta).
    """

    gt: np.ndarray
    displayed: np.ndarray
    flip_map: np.ndarray
    label: str = ""
    holes: np.ndarray | None = None


# --------------------------------------------------------------------------- values


def round_float(x: float, digits: int = FLOAT_DIGITS) -> float | None:
    """``x`` rounded to ``digits`` significant digits; None for NaN / infinity."""
    x = float(x)
    if not math.isfinite(x):
        return None
    if x == 0.0:
        return 0.0
    return float(f"{x:.{digits}g}")


def _plain(value: Any, where: str) -> Any:
    """``value`` as plain JSON-able Python (numpy scalars/arrays, tuples, Paths converted; floats rounded)."""
    if value is None or isinstance(value, (bool, str)):
        return value
    if isinstance(value, (np.bool_,)):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        return round_float(value)
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, np.ndarray):
        return [_plain(v, f"{where}[{i}]") for i, v in enumerate(value.tolist())]
    if isinstance(value, Mapping):
        out = {}
        for k, v in value.items():
            if not isinstance(k, str):
                raise TypeError(f"{where}: keys must be strings, got {k!r}")
            out[k] = _plain(v, f"{where}.{k}" if where else k)
        return out
    if isinstance(value, (list, tuple)):
        return [_plain(v, f"{where}[{i}]") for i, v in enumerate(value)]
    raise TypeError(f"{where or 'value'}: cannot write {type(value).__name__} {value!r} (use numbers, strings, lists, dicts)")


def flatten_record(record: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """``record`` with nested dicts flattened to dotted keys (``{"a": {"b": 1}}`` -> ``{"a.b": 1}``)."""
    out: dict[str, Any] = {}
    for key, value in record.items():
        if not isinstance(key, str):
            raise TypeError(f"record keys must be strings, got {key!r}")
        name = prefix + key
        if isinstance(value, Mapping):
            out.update(flatten_record(value, name + "."))
        else:
            out[name] = value
    return out


def format_figure(value: Any, spec: str) -> str:
    """A figure for a console line: ``format(value, spec)``, or '–' when it is missing (None or NaN)."""
    if value is None or (isinstance(value, (float, np.floating)) and math.isnan(value)):
        return "–"
    return format(value, spec)


def format_value(value: Any) -> str:
    """How a value is shown in the HTML tables: floats with 4 significant digits, None/NaN as '–'."""
    if value is None:
        return "–"
    if isinstance(value, (bool, np.bool_)):
        return str(bool(value))
    if isinstance(value, (int, np.integer)):
        return str(int(value))
    if isinstance(value, (float, np.floating)):
        return "–" if math.isnan(value) else f"{float(value):.4g}"
    return str(value)


def _flatten_all(records: Sequence[Mapping[str, Any]]) -> list[dict[str, Any]]:
    if isinstance(records, Mapping) or isinstance(records, (str, bytes)):
        raise TypeError("records must be a sequence of dicts (one per frame), got a single " + type(records).__name__)
    flat = []
    for i, r in enumerate(records):
        if not isinstance(r, Mapping):
            raise TypeError(f"records[{i}] must be a dict, got {type(r).__name__}")
        flat.append(flatten_record(r))
    return flat


def _columns(flat: Sequence[Mapping[str, Any]]) -> list[str]:
    present = set().union(*(r.keys() for r in flat)) if flat else set()
    core = [c for c in CORE_COLUMNS if c in present]
    return core + sorted(present - set(core))


def _numeric(flat: Sequence[Mapping[str, Any]], key: str) -> np.ndarray:
    """Column ``key`` as float64 (NaN where missing or not a number)."""
    out = np.full(len(flat), np.nan)
    for i, r in enumerate(flat):
        v = r.get(key)
        if isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, (bool, np.bool_)):
            out[i] = float(v)
    return out


def summarize_records(records: Sequence[Mapping[str, Any]]) -> dict[str, dict[str, float]]:
    """Per numeric column: ``{"mean", "p50", "p95", "max", "n"}`` over the frames that have it (NaN/inf ignored).

    Useful to build the summary dict; the HTML report shows it as its statistics table.
    """
    flat = _flatten_all(records)
    stats: dict[str, dict[str, float]] = {}
    for key in _columns(flat):
        if key == "frame":
            continue
        v = _numeric(flat, key)
        v = v[np.isfinite(v)]
        if v.size == 0:
            continue
        stats[key] = {
            "mean": float(np.mean(v)),
            "p50": float(np.percentile(v, 50)),
            "p95": float(np.percentile(v, 95)),
            "max": float(np.max(v)),
            "n": int(v.size),
        }
    return stats


# --------------------------------------------------------------------------- files


def write_frames_csv(path: str | Path, records: Sequence[Mapping[str, Any]]) -> Path:
    """Write one CSV row per record (header = :data:`CORE_COLUMNS` present, then other columns sorted).

    Nested dicts become dotted columns; missing values and non-finite floats
    are empty cells; floats keep :data:`FLOAT_DIGITS` significant digits.
    """
    flat = _flatten_all(records)
    columns = _columns(flat)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w", newline="", encoding="utf-8") as f:
        writer = csv.writer(f, lineterminator="\n")
        writer.writerow(columns)
        for i, r in enumerate(flat):
            row = []
            for c in columns:
                v = _plain(r.get(c), f"records[{i}].{c}")
                if isinstance(v, list):
                    v = json.dumps(v, separators=(",", ":"))
                row.append("" if v is None else v)
            writer.writerow(row)
    return path


def write_summary_json(path: str | Path, summary: Mapping[str, Any]) -> Path:
    """Write ``summary`` as JSON: sorted keys, 2-space indent, floats to :data:`FLOAT_DIGITS` significant digits.

    numpy scalars/arrays and tuples are converted; NaN and infinity become
    ``null``.  The same summary always gives a byte-identical file.
    """
    if not isinstance(summary, Mapping):
        raise TypeError(f"summary must be a dict, got {type(summary).__name__}")
    text = json.dumps(_plain(summary, ""), sort_keys=True, indent=2, allow_nan=False, ensure_ascii=False)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text + "\n", encoding="utf-8")
    return path


# --------------------------------------------------------------------------- images and plots


def flip_heatmap(flip_map: np.ndarray) -> np.ndarray:
    """A FLIP error map (float ``(H, W)`` or ``(H, W, 1)`` in [0, 1]) as a magma-coloured uint8 ``(H, W, 3)`` image."""
    from matplotlib import colormaps

    m = np.asarray(flip_map)
    if m.ndim == 3 and m.shape[2] == 1:
        m = m[:, :, 0]
    if m.ndim != 2:
        raise ValueError(f"flip_map must have shape (H, W) or (H, W, 1), got {m.shape}")
    rgba = colormaps["magma"](np.clip(np.nan_to_num(m.astype(np.float64)), 0.0, 1.0))
    return (rgba[:, :, :3] * 255.0 + 0.5).astype(np.uint8)


def _png_data_uri(image: np.ndarray, what: str) -> str:
    from PIL import Image

    if image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(f"{what} must be sRGB uint8 (H, W, 3), got {image.dtype} {image.shape}")
    buf = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(image), "RGB").save(buf, format="PNG")
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode("ascii")


def _figure(width_in: float = 8.0, height_in: float = 3.0):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width_in, height_in), dpi=100, layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def _figure_data_uri(fig) -> str:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", metadata={"Software": None})
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode("ascii")


def _time_axis(flat: Sequence[Mapping[str, Any]]) -> tuple[np.ndarray, str]:
    t = _numeric(flat, "t")
    if np.isfinite(t).any():
        return t, "time (s)"
    frame = _numeric(flat, "frame")
    if np.isfinite(frame).any():
        return frame, "frame"
    return np.arange(len(flat), dtype=np.float64), "record"


def _has(flat: Sequence[Mapping[str, Any]], key: str) -> bool:
    return bool(np.isfinite(_numeric(flat, key)).any())


def _report_plots(flat: Sequence[Mapping[str, Any]]) -> list[tuple[str, str]]:
    """(title, data URI) of every plot the records allow."""
    x, xlabel = _time_axis(flat)
    plots = []

    if _has(flat, "holes"):
        fig = _figure(8.0, 2.4)
        ax = fig.add_subplot()
        ax.plot(x, 100 * _numeric(flat, "holes"), color="tab:red", lw=1.2, marker=".", ms=3, label="holes")
        for key, color, label in (("holes_smeared", "tab:orange", "of which smeared edge pixels"),
                                  ("holes_interior", "tab:purple", "of which inside the view (cracks)")):
            if _has(flat, key):
                ax.plot(x, 100 * _numeric(flat, key), color=color, lw=1.0, label=label)
        ax.legend(loc="upper right", fontsize=8)
        ax.set_xlabel(xlabel)
        ax.set_ylabel("% of pixels")
        ax.set_title("Holes: pixels shown without content")
        ax.grid(alpha=0.3)
        plots.append(("Holes over time", _figure_data_uri(fig)))

    if _has(flat, "mbps"):
        fig = _figure()
        ax = fig.add_subplot()
        ax.plot(x, _numeric(flat, "mbps"), color="tab:blue", lw=1.2, label="total")
        if _has(flat, "bytes_video") and _has(flat, "bytes_geometry"):
            # Split the rate by the share of video vs geometry bytes in each frame.
            bv, bg = _numeric(flat, "bytes_video"), _numeric(flat, "bytes_geometry")
            total = bv + bg
            with np.errstate(invalid="ignore", divide="ignore"):
                share = np.where(total > 0, bv / total, np.nan)
            ax.plot(x, _numeric(flat, "mbps") * share, color="tab:orange", lw=1.0, label="video")
            ax.plot(x, _numeric(flat, "mbps") * (1 - share), color="tab:green", lw=1.0, label="geometry")
            ax.legend(loc="upper right", fontsize=8)
        ax.set_xlabel(xlabel)
        ax.set_ylabel("Mbit/s")
        ax.set_title("Data rate")
        ax.grid(alpha=0.3)
        plots.append(("Data rate over time", _figure_data_uri(fig)))

    quality = [k for k in ("flip", "ssim", "psnr") if _has(flat, k)]
    if quality:
        fig = _figure(8.0, 2.2 * len(quality))
        axes = fig.subplots(len(quality), 1, sharex=True, squeeze=False)[:, 0]
        styles = {"flip": ("FLIP ↓", "tab:red"), "ssim": ("SSIM ↑", "tab:purple"), "psnr": ("PSNR (dB) ↑", "tab:cyan")}
        for ax, key in zip(axes, quality):
            label, color = styles[key]
            ax.plot(x, _numeric(flat, key), color=color, lw=1.2, marker=".", ms=3)
            ax.set_ylabel(label)
            ax.grid(alpha=0.3)
        axes[0].set_title("Image quality vs ground truth")
        axes[-1].set_xlabel(xlabel)
        plots.append(("Image quality over time", _figure_data_uri(fig)))

    timing = [k for k in ("latency_ms", "pose_error_cm", "pose_error_deg") if _has(flat, k)]
    if timing:
        fig = _figure(8.0, 2.2 * len(timing))
        axes = fig.subplots(len(timing), 1, sharex=True, squeeze=False)[:, 0]
        labels = {"latency_ms": "latency (ms)", "pose_error_cm": "pose error (cm)", "pose_error_deg": "pose error (°)"}
        for ax, key in zip(axes, timing):
            ax.plot(x, _numeric(flat, key), color="tab:gray", lw=1.2)
            ax.set_ylabel(labels[key])
            ax.grid(alpha=0.3)
        axes[0].set_title("Latency and pose error")
        axes[-1].set_xlabel(xlabel)
        plots.append(("Latency and pose error over time", _figure_data_uri(fig)))

    # Stages in order of first appearance (the pipeline order of the stats dict), not alphabetical.
    stages = [c for c in dict.fromkeys(k for r in flat for k in r) if c.startswith(STAGE_PREFIX) and _has(flat, c)]
    if stages:
        means = [float(np.nanmean(_numeric(flat, c))) for c in stages]
        p95 = [float(np.nanpercentile(_numeric(flat, c), 95)) for c in stages]
        fig = _figure(8.0, 0.5 + 0.35 * len(stages))
        ax = fig.add_subplot()
        y = np.arange(len(stages))
        ax.barh(y, p95, color="tab:blue", alpha=0.3, label="p95")
        ax.barh(y, means, color="tab:blue", label="mean")
        ax.set_yticks(y, [c[len(STAGE_PREFIX):] for c in stages])
        ax.invert_yaxis()
        ax.set_xlabel("ms per frame")
        ax.set_title("Time per stage")
        ax.legend(loc="best", fontsize=8)
        ax.grid(alpha=0.3, axis="x")
        plots.append(("Time per stage", _figure_data_uri(fig)))
    return plots


def _series(d: Mapping[str, Any], key: str) -> np.ndarray:
    return np.array([np.nan if v is None else float(v) for v in d.get(key, [])], np.float64)


def timeline_plot(timeline: Mapping[str, Any], flat: Sequence[Mapping[str, Any]] = ()):
    """The figure of a rate-limited run's ``timeline`` (see :mod:`quadcast.sim.evaluate`): the link's capacity,
    the rate sent (per 0.1 s) and the controller's estimate; the operating point of each frame sent; FLIP of the
    scored frames (``flat`` records) and the frame age at every display tick. Returns a matplotlib Figure."""
    sent, display = timeline.get("sent", {}), timeline.get("display", {})
    panels = 3 if timeline.get("points") else 2
    fig = _figure(8.0, 2.2 * panels)
    axes = fig.subplots(panels, 1, sharex=True, squeeze=False)[:, 0]
    ax = axes[0]
    t_sent, size = _series(sent, "t"), _series(sent, "bytes")
    if "link" in timeline:
        ax.step(_series(timeline["link"], "t"), _series(timeline["link"], "mbps"), where="mid", color="black",
                lw=1.2, label="link capacity")
    if t_sent.size:
        edges = np.arange(0.0, float(np.nanmax(t_sent)) + 0.2, 0.1)
        sums, _ = np.histogram(t_sent, edges, weights=size)
        ax.step(edges[1:], sums * 8 / 0.1 / 1e6, where="pre", color="tab:blue", lw=1.0, label="sent (per 0.1 s)")
        cap = _series(sent, "capacity_mbps")
        if np.isfinite(cap).any():
            ax.plot(t_sent, cap, color="tab:orange", lw=1.0, ls="--", label="estimated capacity")
    ax.set_ylabel("Mbit/s")
    ax.set_title("Rate, operating point, quality and frame age")
    ax.legend(loc="upper right", fontsize=7)
    ax.grid(alpha=0.3)
    if panels == 3:
        ax = axes[1]
        names = list(timeline["points"])
        ax.step(t_sent, _series(sent, "point"), where="post", color="tab:green", lw=1.2)
        ax.set_yticks(range(len(names)), names, fontsize=6)
        ax.set_ylabel("point")
        ax.grid(alpha=0.3)
    ax = axes[-1]
    if flat:
        x, _ = _time_axis(flat)
        ax.plot(x, _numeric(flat, "flip"), color="tab:red", lw=1.0, marker=".", ms=3, label="FLIP")
    ax.set_ylabel("FLIP ↓")
    ax.set_xlabel("time (s)")
    ax.grid(alpha=0.3)
    age = _series(display, "age_ms")
    if age.size:
        twin = ax.twinx()
        twin.plot(_series(display, "t"), age, color="tab:gray", lw=0.8, label="frame age")
        twin.set_ylabel("frame age (ms)")
    return fig


# --------------------------------------------------------------------------- HTML

_CSS = """
body { font-family: system-ui, sans-serif; margin: 2em; color: #222; }
table { border-collapse: collapse; margin: 0.5em 0 1.5em; }
th, td { border: 1px solid #ccc; padding: 0.25em 0.6em; text-align: right; }
th:first-child, td:first-child { text-align: left; }
th { background: #f0f0f0; }
img { max-width: 100%; }
.strip { display: flex; gap: 0.5em; align-items: flex-start; }
.strip figure { margin: 0; flex: 1; }
.strip figcaption { font-size: 0.85em; color: #555; }
"""


def _table(header: Sequence[str], rows: Iterable[Sequence[Any]]) -> str:
    out = ["<table>", "<tr>" + "".join(f"<th>{html.escape(str(h))}</th>" for h in header) + "</tr>"]
    for row in rows:
        out.append("<tr>" + "".join(f"<td>{html.escape(format_value(v))}</td>" for v in row) + "</tr>")
    out.append("</table>")
    return "\n".join(out)


def _as_frame_images(item: Any, i: int) -> FrameImages:
    if isinstance(item, FrameImages):
        return item
    if isinstance(item, (tuple, list)) and len(item) in (3, 4, 5):
        return FrameImages(*item)
    raise TypeError(f"worst_frames[{i}] must be a FrameImages or a (gt, displayed, flip_map[, label[, holes]]) tuple, got {type(item).__name__}")


HOLE_COLOR = np.array([255, 0, 255], np.uint8)
"""Holes in the report's strips: magenta."""


def _strip(frame: FrameImages, i: int) -> str:
    fm = np.asarray(frame.flip_map)
    flip_rgb = fm if (fm.dtype == np.uint8 and fm.ndim == 3 and fm.shape[2] == 3) else flip_heatmap(fm)
    gt, shown = np.asarray(frame.gt), np.asarray(frame.displayed)
    if not (gt.shape[:2] == shown.shape[:2] == flip_rgb.shape[:2]):
        raise ValueError(
            f"worst_frames[{i}]: gt {gt.shape}, displayed {shown.shape} and flip_map {fm.shape} must share (H, W)"
        )
    parts = [(gt, "ground truth"), (shown, "displayed"), (flip_rgb, "FLIP error")]
    if frame.holes is not None:
        holes = np.asarray(frame.holes, bool)
        if holes.shape != shown.shape[:2]:
            raise ValueError(f"worst_frames[{i}]: holes {holes.shape} must be the displayed frame's (H, W)")
        marked = np.array(shown, np.uint8, copy=True)
        marked[holes] = HOLE_COLOR
        parts.append((marked, f"holes (magenta, {100 * holes.mean():.2f}%)"))
    figs = "".join(
        f'<figure><img alt="{name}" src="{_png_data_uri(img, f"worst_frames[{i}] {name}")}">'
        f"<figcaption>{name}</figcaption></figure>"
        for img, name in parts
    )
    caption = html.escape(frame.label or f"worst frame {i + 1}")
    return f'<h3>{caption}</h3>\n<div class="strip">{figs}</div>'


def write_report_html(
    path: str | Path,
    summary: Mapping[str, Any],
    records: Sequence[Mapping[str, Any]],
    worst_frames: Sequence[FrameImages | tuple] = (),
    title: str = "quadcast evaluation",
) -> Path:
    """Write a self-contained HTML report (every image an embedded base64 PNG, no external files or links).

    Sections: the summary (flattened key/value table), per-column statistics
    of the records (:func:`summarize_records`), plots over time (data rate,
    FLIP/SSIM/PSNR, latency and pose error, time per stage -- each when the
    records have those columns), and one ground truth / displayed / FLIP-error
    strip per entry of ``worst_frames``.
    """
    if not isinstance(summary, Mapping):
        raise TypeError(f"summary must be a dict, got {type(summary).__name__}")
    flat = _flatten_all(records)
    frames = [_as_frame_images(item, i) for i, item in enumerate(worst_frames)]

    body = [f"<h1>{html.escape(title)}</h1>", f"<p>{len(flat)} frames.</p>", "<h2>Summary</h2>"]
    timeline = summary.get("timeline")
    summary_flat = flatten_record({k: v for k, v in summary.items() if k != "timeline"})
    body.append(_table(["key", "value"], ([k, summary_flat[k]] for k in sorted(summary_flat))))

    stats = summarize_records(records)
    if stats:
        body.append("<h2>Per-frame statistics</h2>")
        body.append(
            _table(
                ["column", "mean", "p50", "p95", "max", "frames"],
                ([k, s["mean"], s["p50"], s["p95"], s["max"], s["n"]] for k, s in stats.items()),
            )
        )

    plots = _report_plots(flat) if flat else []
    if isinstance(timeline, Mapping):
        plots.insert(0, ("Rate, operating point, FLIP and frame age", _figure_data_uri(timeline_plot(timeline, flat))))
    if plots:
        body.append("<h2>Over time</h2>")
        for name, uri in plots:
            body.append(f'<figure><img alt="{html.escape(name)}" src="{uri}"></figure>')

    if frames:
        body.append("<h2>Worst frames</h2>")
        body.extend(_strip(f, i) for i, f in enumerate(frames))

    doc = (
        "<!DOCTYPE html>\n<html lang=\"en\">\n<head>\n<meta charset=\"utf-8\">\n"
        f"<title>{html.escape(title)}</title>\n<style>{_CSS}</style>\n</head>\n<body>\n"
        + "\n".join(body)
        + "\n</body>\n</html>\n"
    )
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(doc, encoding="utf-8")
    return path


# --------------------------------------------------------------------------- sweeps


def _check_rows(rows: Sequence[Mapping[str, Any]]) -> list[Mapping[str, Any]]:
    if isinstance(rows, Mapping):
        raise TypeError("rows must be a sequence of dicts, got a single dict")
    rows = list(rows)
    for i, r in enumerate(rows):
        if not isinstance(r, Mapping):
            raise TypeError(f"rows[{i}] must be a dict, got {type(r).__name__}")
        if "method" not in r:
            raise ValueError(f"rows[{i}] has no 'method' key: {dict(r)!r}")
    return rows


def _cell(key: str, value: Any) -> str:
    if value is None or (isinstance(value, (float, np.floating)) and math.isnan(value)):
        return "–"
    if key in _COMPARISON_FORMATS and isinstance(value, (int, float, np.integer, np.floating)):
        return _COMPARISON_FORMATS[key].format(float(value))
    if isinstance(value, (float, np.floating)):
        return f"{float(value):g}"
    return str(value).replace("|", "\\|")


def write_comparison_table(rows: Sequence[Mapping[str, Any]]) -> str:
    """A markdown table of a sweep, like QUASAR's Table 4: one line per row, columns :data:`COMPARISON_COLUMNS`.

    Rows are dicts with ``method`` (required) and any of ``latency_ms``,
    ``viewcell`` (a number in metres or a label), ``mbps``, ``flip``,
    ``ssim``, ``psnr``; missing values show as '–'.  Rows keep their order.
    """
    rows = _check_rows(rows)
    lines = [
        "| " + " | ".join(h for _, h in COMPARISON_COLUMNS) + " |",
        "| " + " | ".join("---" if k == "method" else "---:" for k, _ in COMPARISON_COLUMNS) + " |",
    ]
    for r in rows:
        lines.append("| " + " | ".join(_cell(k, r.get(k)) for k, _ in COMPARISON_COLUMNS) + " |")
    return "\n".join(lines) + "\n"


_MARKERS = ("o", "s", "^", "D", "v", "P", "X", "*", "<", ">")


def plot_quality_vs_rate(rows: Sequence[Mapping[str, Any]], path: str | Path) -> Path:
    """Plot FLIP against data rate (log x), one marker and colour per method, like QUASAR's Fig. 12; save to ``path``.

    Every row needs ``method``, ``mbps`` (> 0) and ``flip``; a method's
    points are joined in order of rate.  The file format follows the
    extension (``.png``, ``.svg``, ``.pdf``).
    """
    rows = _check_rows(rows)
    if not rows:
        raise ValueError("plot_quality_vs_rate needs at least one row")
    by_method: dict[str, list[tuple[float, float]]] = {}
    for i, r in enumerate(rows):
        for key in ("mbps", "flip"):
            v = r.get(key)
            if not isinstance(v, (int, float, np.integer, np.floating)) or not math.isfinite(v):
                raise ValueError(f"rows[{i}] ({r['method']}): {key} must be a finite number, got {v!r}")
        if r["mbps"] <= 0:
            raise ValueError(f"rows[{i}] ({r['method']}): mbps must be > 0 for a log axis, got {r['mbps']!r}")
        by_method.setdefault(str(r["method"]), []).append((float(r["mbps"]), float(r["flip"])))

    fig = _figure(6.0, 4.0)
    ax = fig.add_subplot()
    for k, (method, points) in enumerate(by_method.items()):
        points.sort()
        ax.plot(
            [p[0] for p in points],
            [p[1] for p in points],
            marker=_MARKERS[k % len(_MARKERS)],
            color=f"C{k % 10}",
            lw=1.0,
            ms=7,
            label=method,
        )
    ax.set_xscale("log")
    ax.set_xlabel("data rate (Mbit/s, log)")
    ax.set_ylabel("FLIP ↓")
    ax.set_title("Quality vs data rate")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, metadata={"Software": None} if path.suffix.lower() == ".png" else None)
    return path
