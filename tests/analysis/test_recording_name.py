"""Every recording carries a name, which the viewer lists it by: its file's name and what it holds (the target, the
runs; a tracker's run its title). Before, no recording had one (no properties are sent), so the files of a folder
`envisat view` opens (a CubeSat's mc.rrd, est.rrd and sim.rrd) were listed alike, as envisat_pose."""

import os
import sys

import numpy as np

from envisat_pose.analysis import recording
from envisat_pose.analysis.recording import TrackRecorder, read_recording
from envisat_pose.geometry import load_camera
from envisat_pose.target import load_target

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))  # the folder's own helpers
from test_recording_blueprint import estimates  # noqa: E402

CUBESAT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", "models", "cubesat_3u.xml")


def name_of(path) -> str:
    static, _ = read_recording(str(path))
    (name,) = static["/__properties"]["RecordingInfo:name"]
    return name


def test_every_recording_is_named_by_its_file_and_what_it_holds(tmp_path):
    cubesat = load_target(CUBESAT)
    est = estimates(R=3)
    recording.write_estimates_recording(str(tmp_path / "est.rrd"), est, target=cubesat)
    assert name_of(tmp_path / "est.rrd") == "est.rrd: cubesat_3u estimates, 3 runs"
    T = len(est.t_s)
    recording.write_campaign_recording(str(tmp_path / "mc.rrd"), est.t_s, est.x_true[0], est.x_hat[0], est.P[0],
                                       est.x_hat - est.x_true, np.ones((T, 12)), None, target=cubesat,
                                       nees_mean=np.full(T, 12.0), nees_bounds=np.array([8.0, 17.0]), runs=40)
    assert name_of(tmp_path / "mc.rrd") == "mc.rrd: cubesat_3u Monte Carlo, 40 runs"
    recording.write_estimates_recording(str(tmp_path / "envisat.rrd"), estimates(R=1))  # the default target
    assert name_of(tmp_path / "envisat.rrd") == "envisat.rrd: envisat estimates, 1 run"

    rec = TrackRecorder(f"save:{tmp_path / 'recording.rrd'}", load_camera().scaled(64, 64), with_truth=False,
                        title="envisat track cubesat_3u: frames", target=cubesat)
    rec.close()
    assert name_of(tmp_path / "recording.rrd") == "recording.rrd: envisat track cubesat_3u: frames"
