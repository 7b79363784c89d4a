"""The viewer page in a real browser: Debian's Chromium driven by Playwright (``quadcast bench browser``, the
browser tests).

Playwright's own browser download does not work everywhere (it fetches a build of its own), so it drives the
system's ``/usr/bin/chromium`` (Debian's package ``chromium``; ``make test`` / ``make bench`` install it as root).
Headless Chromium renders WebGL2 on SwiftShader (``--enable-unsafe-swiftshader``, a CPU renderer: expect low
frame rates on a small machine) and decodes H.264 with WebCodecs. Playwright gives every launch a fresh profile
(``--user-data-dir``); the background-networking flags keep Chromium from calling home on a closed network.
"""
from __future__ import annotations

import os
import shutil
import statistics
import time
from contextlib import contextmanager
from pathlib import Path

__all__ = ["CHROMIUM", "chromium_args", "chromium_missing", "launch_chromium", "bench_browser", "page_url"]

CHROMIUM = "/usr/bin/chromium"


def chromium_args() -> list[str]:
    args = ["--headless", "--enable-unsafe-swiftshader", "--disable-background-networking",
            "--disable-component-update", "--disable-sync", "--no-first-run", "--disable-quic",
            "--autoplay-policy=no-user-gesture-required"]
    if hasattr(os, "geteuid") and os.geteuid() == 0:
        args.append("--no-sandbox")          # Chromium's sandbox refuses to run as root
    return args


def chromium_missing() -> str | None:
    """Why the browser cannot run here (None when it can)."""
    if not (Path(CHROMIUM).is_file() and os.access(CHROMIUM, os.X_OK)) and not shutil.which("chromium"):
        return (f"Debian's chromium is not installed ({CHROMIUM}); `make test` installs it as root, otherwise run "
                f"`sudo apt-get install chromium`")
    try:
        import playwright  # noqa: F401
    except ImportError:
        return "the Python package playwright is not installed (pip install -e '.[test]' or '.[browser]')"
    return None


@contextmanager
def launch_chromium():
    """A headless Chromium (Playwright ``Browser``), closed on exit."""
    from playwright.sync_api import sync_playwright
    missing = chromium_missing()
    if missing:
        raise RuntimeError(missing)
    executable = CHROMIUM if Path(CHROMIUM).is_file() else shutil.which("chromium")
    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=executable, headless=True, args=chromium_args())
        try:
            yield browser
        finally:
            browser.close()


def page_url(port: int, size: tuple[int, int], trace: str | None = "builtin:walk", host: str = "127.0.0.1",
             token: str = "", **extra) -> str:
    """The viewer's address; the token goes in the fragment, which the browser never sends to the server."""
    query = ([f"trace={trace}"] if trace else []) + [f"size={size[0]}x{size[1]}"] + [f"{k}={v}" for k, v in extra.items()]
    return f"http://{host}:{port}/?{'&'.join(query)}" + (f"#token={token}" if token else "")


def bench_browser(sizes: list[tuple[int, int]], scene: str = "builtin:courtyard", duration: float = 20.0,
                  warmup: float = 3.0, screenshot: Path | None = None, out_dir: Path | None = None,
                  trace: str = "builtin:walk") -> list[dict]:
    """The viewer page following a built-in trace (builtin:walk) against a live server on loopback (both on this machine): per size,
    the page's display fps, frame age (display time - the time the frame was predicted for, ms), frames applied
    per second and Mbps, from ``window.quadcast.stats`` sampled every 0.5 s over ``duration`` s after a warm-up."""
    import tempfile

    from quadcast.cli.demo import LISTENING, Child, quadcast_argv

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        logs = Path(out_dir or tmp)
        logs.mkdir(parents=True, exist_ok=True)
        server = Child("server", quadcast_argv("server", "--port", 0, "--scene", scene, "-v"), logs / "server.log")
        try:
            port = int(server.wait_for(LISTENING, 180).group(2))
            with launch_chromium() as browser:
                for w, h in sizes:
                    rows.append(_bench_size(browser, port, (w, h), duration, warmup, screenshot, trace))
        finally:
            server.stop()
    return rows


def _bench_size(browser, port: int, size: tuple[int, int], duration: float, warmup: float,
                screenshot: Path | None, trace: str) -> dict:
    w, h = size
    page = browser.new_page(viewport={"width": w, "height": h})
    errors: list[str] = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
    try:
        page.goto(page_url(port, size, trace))
        page.wait_for_function("window.quadcast && window.quadcast.stats.framesApplied > 0", timeout=120_000)
        time.sleep(warmup)
        read = "({...window.quadcast.stats})"
        first, t0 = page.evaluate(read), time.monotonic()
        samples = []
        while time.monotonic() - t0 < duration:
            time.sleep(0.5)
            samples.append(page.evaluate(read))
        last, elapsed = samples[-1], time.monotonic() - t0
        if screenshot is not None:
            Path(screenshot).parent.mkdir(parents=True, exist_ok=True)
            page.screenshot(path=str(screenshot))
    finally:
        page.close()
    ages = [s["frameAgeMs"] for s in samples if s["frameAgeMs"] is not None]
    row = {"size": f"{w}x{h}", "trace": trace, "seconds": elapsed,
           "fps": (last["framesDisplayed"] - first["framesDisplayed"]) / elapsed,
           "frames_applied_per_s": (last["framesApplied"] - first["framesApplied"]) / elapsed,
           "frame_age_ms_median": statistics.median(ages) if ages else None,
           "frame_age_ms_p90": statistics.quantiles(ages, n=10)[-1] if len(ages) >= 2 else None,
           "mbps": statistics.mean(s["mbps"] for s in samples),
           "frames_received": last["framesReceived"], "frames_rejected": last["framesRejected"],
           "reference_requests": last["referenceRequests"], "page_errors": errors}
    f = lambda v, spec: "n/a" if v is None else format(v, spec)  # noqa: E731
    print(f"browser {row['size']} {trace}: {row['fps']:.1f} fps displayed, frame age median "
          f"{f(row['frame_age_ms_median'], '.0f')} ms (p90 {f(row['frame_age_ms_p90'], '.0f')} ms), "
          f"{row['frames_applied_per_s']:.1f} frames/s applied, {row['mbps']:.2f} Mbps, "
          f"{len(errors)} page errors  [{elapsed:.0f} s, headless Chromium on SwiftShader, server on the same "
          f"machine]", flush=True)
    return row
