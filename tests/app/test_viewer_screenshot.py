"""A closed-loop recording opens in the real Rerun web viewer: `envisat view RUN_DIR --web` serves it on 127.0.0.1,
headless Chromium (SwiftShader, see the platform notes) loads the page and saves a screenshot, and the screenshot
shows the recording's own content rather than the loading screen: the camera image (a large black frame), the
error plots (their red 3-sigma bands) and the 3D view (the estimate's blue wireframe of the target).

Chromium is installed by `make test` (scripts/setup.sh with WITH_VIEWER_CHECK=1); without it the test skips.
The screenshot is taken in real time through the DevTools protocol (not with --screenshot and a virtual-time
budget, which on a loaded machine often ends on the loading screen)."""

import os
import shutil
import subprocess
import sys
import time

import cv2
import numpy as np
import pytest

from envisat_pose.analysis import viewer as view
from envisat_pose.pipelines.runs import closed_loop as loop

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
from test_view import free_ports, listeners, rerun_env, wait_http  # noqa: E402,F401  (rerun_env: a fixture)

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")


def chromium_screenshot(url: str, out_png: str, profile_dir: str, ready, timeout_s: float = 240.0) -> None:
    """Headless Chromium with software GL (the flags of the platform notes) opens url; a screenshot is taken every
    few seconds of real time, through the DevTools protocol on a 127.0.0.1 port (tornado's websocket client, a
    dependency of dask.distributed), until ready(png) holds or timeout_s passes. Real time, not Chromium's
    virtual time budget: on a loaded machine the viewer's bundle compiles for longer than any fixed budget."""
    import asyncio
    import base64
    import json
    import urllib.request

    (debug_port,) = free_ports(1)
    cmd = [CHROMIUM, "--headless=new", "--no-sandbox", "--use-gl=angle", "--use-angle=swiftshader",
           "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist", "--disable-quic", "--no-first-run",
           "--disable-background-networking", "--disable-component-update", "--disable-sync",
           f"--user-data-dir={profile_dir}", "--window-size=1600,1000", "--remote-debugging-address=127.0.0.1",
           f"--remote-debugging-port={debug_port}", "about:blank"]
    proc = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            start_new_session=True)

    async def drive(ws_url: str) -> None:
        from tornado.websocket import websocket_connect

        conn = await websocket_connect(ws_url, max_message_size=256 * 2**20)
        ids = iter(range(1, 10**6))

        async def call(method: str, **params):
            i = next(ids)
            await conn.write_message(json.dumps({"id": i, "method": method, "params": params}))
            while True:
                msg = await conn.read_message()
                assert msg is not None, "the DevTools connection closed"
                reply = json.loads(msg)
                if reply.get("id") == i:
                    assert "error" not in reply, reply["error"]
                    return reply["result"]

        await call("Page.enable")
        await call("Page.navigate", url=url)
        end = time.monotonic() + timeout_s
        while True:
            await asyncio.sleep(4.0)
            shot = await call("Page.captureScreenshot", format="png")
            with open(out_png, "wb") as fh:
                fh.write(base64.b64decode(shot["data"]))
            if ready(out_png) or time.monotonic() > end:
                break
        conn.close()

    try:
        deadline = time.monotonic() + 60
        pages = []
        while time.monotonic() < deadline and not pages:
            try:
                with urllib.request.urlopen(f"http://127.0.0.1:{debug_port}/json/list", timeout=5) as r:
                    pages = [p for p in json.loads(r.read()) if p.get("type") == "page"]
            except OSError:
                time.sleep(0.5)
        assert pages, "headless Chromium did not open its DevTools port"
        asyncio.run(drive(pages[0]["webSocketDebuggerUrl"]))
    finally:
        view.stop_viewer(proc)


def shows_the_recording(png: str) -> dict:
    """Pixel counts of what only the loaded recording draws (BGR thresholds)."""
    img = cv2.imread(png, cv2.IMREAD_COLOR)
    b, g, r = (img[..., k].astype(int) for k in range(3))
    black = (img.max(axis=-1) < 6)  # the camera frame's dark sky (the loading screen is grey 13-17)
    red = (r > 170) & (g < 90) & (b < 90)  # the x components' error series and their +-3 sigma
    blue = (b > 100) & (b - r > 50) & (b - g > 30)  # the estimate's wireframe in 3D (EST_RGB)
    return {"black": int(black.sum()), "red": int(red.sum()), "blue": int(blue.sum()),
            "colours": int(len(np.unique(img.reshape(-1, 3), axis=0))), "pixels": int(img.shape[0] * img.shape[1])}


def looks_loaded(png: str) -> bool:
    c = shows_the_recording(png)
    return c["black"] > 0.04 * c["pixels"] and c["red"] > 300 and c["blue"] > 100 and c["colours"] > 2000


@pytest.mark.slow
@pytest.mark.skipif(CHROMIUM is None, reason="chromium is not installed (make test installs it as root)")
def test_the_recording_opens_in_the_web_viewer(tmp_path, detector_weights, rerun_env):  # noqa: F811 (a fixture)
    from envisat_pose.pipelines.runs.run_config import RunConfig

    cfg = RunConfig(scenario="default", duration_s=6.0, weights=detector_weights, workers=1, warm_start=True)
    run_dir = tmp_path / "run"
    loop.run_closed_loop(cfg, str(run_dir), progress=False)
    port, web_port = free_ports(2)
    proc = view.start_viewer(view.viewer_command(view.recordings(str(run_dir)), web=True, port=port,
                                                 web_port=web_port), env=rerun_env, quiet=True)
    shot = tmp_path / "viewer.png"
    try:
        assert wait_http(f"http://127.0.0.1:{web_port}/", proc) == 200
        deadline = time.monotonic() + 60  # the recording's gRPC server too (it starts after the web server)
        while not listeners(port) and time.monotonic() < deadline:
            time.sleep(0.5)
        assert listeners(port), f"the viewer's gRPC port {port} does not listen"
        chromium_screenshot(view.web_url(port, web_port), str(shot), str(tmp_path / "chrome"), looks_loaded)
    finally:
        view.stop_viewer(proc)
    counts = shows_the_recording(str(shot))
    print(counts)
    assert counts["black"] > 0.04 * counts["pixels"], "no camera image in the screenshot"
    assert counts["red"] > 300, "no error plots with their 3-sigma bands"
    assert counts["blue"] > 100, "no 3D view of the estimated target (its blue wireframe)"
    assert counts["colours"] > 2000


def write_long_recording(path, frames=600, with_error=150):
    """A 600 s tracker recording at 1 Hz (the demo's length) whose error plots hold data only in the first 150 s
    (tracking, with a truth), the tracker's status to the end: a plot that shows the whole run draws the red
    x-component error series over its first quarter; one that shows a trailing window (the last ~50 s) draws none."""
    from envisat_pose.analysis.recording import TrackRecorder
    from envisat_pose.geometry import load_camera

    rec = TrackRecorder(f"save:{path}", load_camera().scaled(64, 64), with_truth=True, title="whole-run check")
    x = np.zeros(12)
    x[1] = 50.0
    P = np.diag(np.tile([4.0, 1.0, 0.25], 4)) * 1e-4  # x's 3-sigma lines apart from y's and z's
    for k in range(frames):
        status = 1 if k < with_error else 0
        x_hat = x + 0.05 * np.sin(0.1 * k) * np.tile([1.0, 0.0, 0.0], 4)  # an error in the x components only
        rec.log_frame(k, {"t_s": float(k), "x_hat": x_hat, "P": P, "status": status, "p_best": 1.0,
                          "nis": 1.0, "nis_dof": 2, "corners_px": np.full((8, 2), np.nan),
                          "visible": np.zeros(8, bool), "rejected": np.zeros(8, bool), "roi_px": np.full(3, np.nan)},
                      None, x_true=x)
    rec.close()


@pytest.mark.slow
@pytest.mark.skipif(CHROMIUM is None, reason="chromium is not installed (make test installs it as root)")
def test_every_plot_shows_the_whole_run_at_load(tmp_path, rerun_env):  # noqa: F811 (a fixture)
    """A 600 s recording opened in the web viewer: the error plots show the first 150 s of data (red x-component
    series), i.e. their time axis spans the whole run at load, not a trailing window at the time cursor."""
    rrd = tmp_path / "long.rrd"
    write_long_recording(str(rrd))
    port, web_port = free_ports(2)
    proc = view.start_viewer(view.viewer_command([str(rrd)], web=True, port=port, web_port=web_port), env=rerun_env,
                             quiet=True)
    shot = tmp_path / "viewer.png"

    def red_shown(png):
        return shows_the_recording(png)["red"] > 300

    try:
        assert wait_http(f"http://127.0.0.1:{web_port}/", proc) == 200
        deadline = time.monotonic() + 60
        while not listeners(port) and time.monotonic() < deadline:
            time.sleep(0.5)
        chromium_screenshot(view.web_url(port, web_port), str(shot), str(tmp_path / "chrome"), red_shown,
                            timeout_s=150.0)
    finally:
        view.stop_viewer(proc)
    counts = shows_the_recording(str(shot))
    print(counts)
    assert counts["red"] > 300, "the error plots do not show the run's first 150 s: not the whole run at load"
