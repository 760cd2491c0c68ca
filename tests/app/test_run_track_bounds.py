"""Finite values no `envisat run`, `track` or `adapt` job can mean, refused when the config is built, in one line
naming the field, its value and what is expected, before any frame is made: tracker thresholds that bounded
nothing physical or broke the numbers (max_gap_s, huber, start_cov_factor, the bank's and the array cue's nats,
min_target_px, max_rate_deg_s, max_speed_m_s, recall_s, recall_cov_factor at 1e300; huber, max_gap_s, min_target_px
at 1e-300: a fit that never left its guess, a window that restarts at every frame), a window of 2^63 - 1 frames (a
numpy error at the first start), a run shorter than one frame or whose frames lie 1e300 s apart (refused after the
run began, or naming a field the user never set), a track's frame rate of 1e300 Hz or 1e-300 Hz, adapt's 2^63 - 1
threads (a ValueError at the fine-tune). Values meaning "off" by design stay accepted."""

import os
import sys

import pytest

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))  # the folder's own helpers
from refusals import refused  # noqa: E402

from envisat_pose.config import ConfigError  # noqa: E402

BIG = 2**63 - 1  # TOML's largest integer


@pytest.mark.parametrize("kind, text, words", [
    ("run", "[tracker.acquire]\nmax_gap_s = 1e300\n", ("tracker.acquire.max_gap_s = 1e+300: expected", "1e+06] s")),
    ("run", "[tracker.acquire]\nmax_gap_s = 1e-300\n", ("tracker.acquire.max_gap_s = 1e-300: expected", "[0.0001,")),
    ("run", "[tracker.acquire]\nstart_cov_factor = 1e300\n", ("start_cov_factor = 1e+300: expected", "[1, 1e+48]")),
    ("run", "[tracker.fit]\nhuber = 1e300\n", ("tracker.fit.huber = 1e+300: expected", "least squares")),
    ("run", "[tracker.fit]\nhuber = 1e-300\n", ("tracker.fit.huber = 1e-300: expected", "never leaves its guess")),
    ("run", "[tracker.bank]\nappearance_max_log = 1e300\n", ("appearance_max_log = 1e+300: expected", "709.8")),
    ("run", "[tracker.bank]\nframe_max_log = 1e300\n", ("tracker.bank.frame_max_log = 1e+300: expected", "709.8")),
    ("run", "[tracker.array_cue]\nper_frame = 1e300\n", ("tracker.array_cue.per_frame = 1e+300: expected", "709.8")),
    ("run", "[tracker.array_cue]\nmax_log = 1e300\n", ("tracker.array_cue.max_log = 1e+300: expected", "709.8")),
    ("run", "[tracker.roi]\nconverged_pos_sigma_m = 1e300\n", ("converged_pos_sigma_m = 1e+300: expected", "1e+12")),
    ("run", "[tracker.roi]\nconverged_att_sigma_deg = 1e300\n", ("converged_att_sigma_deg = 1e+300: expected", "180")),
    ("run", f"[tracker.integrity]\nwindow = {BIG}\n", (f"tracker.integrity.window = {BIG}: expected", "200000")),
    ("run", "[tracker.integrity]\nmin_target_px = 1e300\n", ("min_target_px = 1e+300: expected", "[1, 4096] px")),
    ("run", "[tracker.integrity]\nmin_target_px = 1e-300\n", ("min_target_px = 1e-300: expected", "[1, 4096] px")),
    ("run", "[tracker.integrity]\nmax_rate_deg_s = 1e300\n", ("max_rate_deg_s = 1e+300: expected", "28648 deg/s")),
    ("run", "[tracker.integrity]\nmax_speed_m_s = 1e300\n", ("max_speed_m_s = 1e+300: expected", "22360 m/s")),
    ("run", "[tracker.integrity]\nrecall_s = 1e300\n", ("tracker.integrity.recall_s = 1e+300: expected", "0: no memory")),
    ("run", "[tracker.integrity]\nrecall_cov_factor = 1e300\n", ("recall_cov_factor = 1e+300: expected", "[1, 1e+48]")),
    ("run", "duration_s = 1e-300\n", ("duration_s = 1e-300: expected", "one frame interval (1 / rate_hz = 1 s)")),
    ("run", "rate_hz = 1e-300\n", ("rate_hz = 1e-300: expected", "[1e-06, 10] Hz")),
    ("track", "[tracker.fit]\nhuber = 1e300\n", ("tracker.fit.huber = 1e+300: expected", "least squares")),
    ("track", "rate_hz = 1e300\n", ("rate_hz = 1e+300: expected", "[1e-06, 10000] Hz")),
    ("track", "rate_hz = 1e-300\n", ("rate_hz = 1e-300: expected", "[1e-06, 10000] Hz")),
])
def test_a_value_no_run_or_track_can_mean_is_refused_naming_it(tmp_path, kind, text, words):
    """Through the public builder the verbs call (resolve_job with a config file), before any frame or truth."""
    from envisat_pose.pipelines.jobs import resolve_job

    cfg = tmp_path / "edge.toml"
    cfg.write_text(text)
    with pytest.raises(ConfigError) as err:
        resolve_job(kind, "default", str(cfg))
    assert all(w in str(err.value) for w in words), str(err.value)


def test_the_track_verb_refuses_a_frame_rate_no_camera_has_in_one_line(tmp_path, capsys):
    """`envisat track --rate-hz 1e300` over three image files: one line naming the flag (before, the frame count
    was what it refused, after reading them; a rate of 1e-300 Hz the frames' times refuse, beyond the recording's
    clock)."""
    import cv2
    import numpy as np

    frames = tmp_path / "frames"
    frames.mkdir()
    for k in range(3):
        cv2.imwrite(str(frames / f"f_{k}.png"), np.zeros((64, 64), np.uint8))
    out = tmp_path / "out"
    refused(["track", "--images", str(frames), "--rate-hz", "1e300", "--quiet", "--out", str(out)], capsys, out,
            "--rate-hz 1e+300: expected", "or 0: a video's own")


def test_adapt_refuses_more_threads_than_any_job_takes():
    """2^63 - 1 torch threads: a ValueError at the fine-tune, after the tracking runs, before."""
    from envisat_pose.pipelines.adaptation.adapt import AdaptConfig

    with pytest.raises(ConfigError, match=rf"threads = {BIG}: expected 0 to 256 threads"):
        AdaptConfig(threads=BIG)


def test_off_values_and_the_bounds_themselves_stay_accepted():
    """What means "off" by design (frame_max_log 0: no bound, recall_s 0: no memory, array_cue.per_frame 0, a
    video's own rate 0), the bounds (least squares at huber 1e6, a gap of 1e6 s, a window of the longest run), and a
    run of one frame interval."""
    from envisat_pose.pipelines.runs.run_config import RunConfig
    from envisat_pose.pipelines.runs.track import TrackConfig
    from envisat_pose.pipelines.tracking.tracker import TrackerConfig

    TrackerConfig(bank={"frame_max_log": 0.0, "appearance_max_log": 0.0}, array_cue={"per_frame": 0.0},
                  integrity={"recall_s": 0.0, "window": 200_000, "max_rate_deg_s": 28000.0, "min_target_px": 1.0},
                  fit={"huber": 1e6}, acquire={"max_gap_s": 1e6, "start_cov_factor": 1e48})
    TrackConfig(rate_hz=0.0)
    TrackConfig(rate_hz=1e4, tracker={"integrity": {"recall_s": 1e6}})
    RunConfig(duration_s=1.0, rate_hz=1.0)
    RunConfig(duration_s=1e6, rate_hz=1e-6)
