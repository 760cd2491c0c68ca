"""A closed-loop recording opens in the real Rerun web viewer: `envisat view RUN_DIR --web` serves it on 127.0.0.1,
headless Chromium (SwiftShader, see the platform notes) loads the page and saves a screenshot, and the screenshot
shows the recording's own content rather than the loading screen: the camera image (a large black frame), the
error plots (their red 3-sigma bands) and the 3D view (the solar array's blue cells).

Chromium is installed by `make test` (scripts/setup.sh with WITH_VIEWER_CHECK=1); without it the test skips."""

import os
import shutil
import subprocess
import sys
import time

import cv2
import numpy as np
import pytest

from envisat_pose.app import run as loop
from envisat_pose.app import view

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
from test_view import free_ports, listeners, rerun_env, wait_http  # noqa: E402,F401  (rerun_env: a fixture)

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")


def chromium_screenshot(url: str, out_png: str, profile_dir: str, timeout_s: int = 300) -> None:
    """Headless Chromium with software GL (the flags of the platform notes), one screenshot of url."""
    cmd = [CHROMIUM, "--headless=new", "--no-sandbox", "--use-gl=angle", "--use-angle=swiftshader",
           "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist", "--disable-quic", "--no-first-run",
           "--disable-background-networking", "--disable-component-update", "--disable-sync",
           f"--user-data-dir={profile_dir}", "--window-size=1600,1000", "--virtual-time-budget=240000",
           f"--screenshot={out_png}", url]
    subprocess.run(cmd, check=True, capture_output=True, timeout=timeout_s, start_new_session=True)


def shows_the_recording(png: str) -> dict:
    """Pixel counts of what only the loaded recording draws (BGR thresholds)."""
    img = cv2.imread(png, cv2.IMREAD_COLOR)
    b, g, r = (img[..., k].astype(int) for k in range(3))
    black = (img.max(axis=-1) < 6)  # the camera frame's dark sky (the loading screen is grey 13-17)
    red = (r > 170) & (g < 90) & (b < 90)  # the +-3 sigma series
    blue = (b > 100) & (b - r > 50) & (b - g > 30)  # the solar array's cells in 3D
    return {"black": int(black.sum()), "red": int(red.sum()), "blue": int(blue.sum()),
            "colours": int(len(np.unique(img.reshape(-1, 3), axis=0))), "pixels": int(img.shape[0] * img.shape[1])}


@pytest.mark.slow
@pytest.mark.skipif(CHROMIUM is None, reason="chromium is not installed (make test installs it as root)")
def test_the_recording_opens_in_the_web_viewer(tmp_path, detector_weights, rerun_env):
    from envisat_pose.app.scenarios import job_defaults
    from envisat_pose.config import from_dict

    loop._stage_types()
    data = {"scenario": "default", "duration_s": 6.0, "weights": detector_weights, "workers": 1,
            "filter": {**loop.LOOP_FILTER, **job_defaults("default")["filter"]}}
    cfg = loop.finish_config(from_dict(loop.RunConfig, data))
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
        # the page's virtual time can run out before the viewer's bundle has loaded (it compiles in real time):
        # then the screenshot shows the loading screen; look again a little later
        for attempt in range(8):
            chromium_screenshot(view.web_url(port, web_port), str(shot), str(tmp_path / "chrome"))
            counts = shows_the_recording(str(shot))
            print(attempt, counts)
            if counts["colours"] > 2000:
                break
            time.sleep(5)
    finally:
        view.stop_viewer(proc)
    assert counts["black"] > 0.04 * counts["pixels"], "no camera image in the screenshot"
    assert counts["red"] > 300, "no error plots with their 3-sigma bands"
    assert counts["blue"] > 100, "no 3D view of the target's solar array"
    assert counts["colours"] > 2000
