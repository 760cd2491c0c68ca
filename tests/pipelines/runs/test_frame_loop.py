"""The per-frame loop shared by `envisat run` and `envisat track` (pipelines/runs/frame_loop.py), with a fake tracker
and recorder: what it stores per frame, the stage times by name, and that the recorder is closed on an error; with
`overlap`, the same rows, the next frame made while the tracker steps the last, and errors from either side."""

import dataclasses
import os
import threading

import numpy as np
import pytest

from envisat_pose.pipelines.runs.frame_loop import FrameInput, run_frames
from envisat_pose.pipelines.runs.rows import STAGES, RunRows, timing_by_status
from envisat_pose.pipelines.tracking.tracker import TrackEstimate
from envisat_pose.status import STATUSES


class FakeTracker:
    """A pose (x_hat = t_s) on frames with an image, none on frames without; detection 0.25 s where it detects."""

    def __init__(self, fail_at=None):
        self.calls, self.fail_at = [], fail_at

    def step(self, t_s, image, window_px=None):
        self.calls.append((t_s, image is None))
        if t_s == self.fail_at:
            raise RuntimeError("tracker failed")
        seen = image is not None
        timing = {"detection": 0.25, "filtering": 0.5} if seen else {"filtering": 0.125}
        return TrackEstimate(t_s=t_s, status="tracking" if seen else "coasting", x_hat=np.full(12, t_s),
                             P=np.eye(12), hypotheses=np.zeros((1, 12)), probabilities=np.ones(1), detection=None,
                             naming=0, measured=np.zeros(8, bool), rejected=np.zeros(8, bool), nis=1.0, nis_dof=2,
                             roi_px=None, converged=True, timing_s=timing)


class FakeRecorder:
    def __init__(self):
        self.frames, self.closed = [], False

    def log_frame(self, k, est, image, jpeg_quality, x_true=None, corners_true_px=None, in_frame=None):
        self.frames.append((k, est["t_s"], image is None, jpeg_quality, x_true))

    def close(self):
        self.closed = True


def frames(n=3, dark=(1,)):
    image = np.zeros((4, 4), np.uint8)
    for k in range(n):
        yield FrameInput(k, 0.5 * k, None if k in dark else image, (0.01 * k, 0.02, 0.03), x_true=np.full(12, k))


@pytest.mark.parametrize("overlap", [False, True])
def test_the_loop_fills_each_row_and_its_stage_times_by_name(tmp_path, overlap):
    """Three frames (the second without an image) over chunks of two: the rows on file hold each estimate, the
    skipped frame, and the stage times in STAGES' columns; the reductions sum them; the recorder saw every frame."""
    run_dir = str(tmp_path / "run")
    tracker, recorder = FakeTracker(), FakeRecorder()
    sums = run_frames(tracker, frames(), RunRows(run_dir, 3, chunk=2), recorder, jpeg_quality=55, overlap=overlap)
    assert tracker.calls == [(0.0, False), (0.5, True), (1.0, False)]
    col = {k: np.load(os.path.join(run_dir, f"{k}.npy")) for k in ("x_hat", "status", "skipped", "timing_s")}
    assert col["x_hat"][:, 0].tolist() == [0.0, 0.5, 1.0]
    assert [STATUSES[s] for s in col["status"]] == ["tracking", "coasting", "tracking"]
    assert col["skipped"].tolist() == [False, True, False]
    t = col["timing_s"]
    assert t[:, STAGES.index("simulation")].tolist() == [0.0, 0.01, 0.02]
    assert (t[:, STAGES.index("rendering")] == 0.02).all() and (t[:, STAGES.index("camera")] == 0.03).all()
    assert t[:, STAGES.index("detection")].tolist() == [0.25, 0.0, 0.25]  # none timed on the skipped frame
    assert t[:, STAGES.index("filtering")].tolist() == [0.5, 0.125, 0.5]
    assert (t[:, STAGES.index("recording")] >= 0).all()
    assert sums["frames"] == 3 and sums["frames_skipped_eclipse"] == 1
    assert np.allclose(sums["timing_s"], t.sum(axis=0))
    assert [f[:4] for f in recorder.frames] == [(0, 0.0, False, 55), (1, 0.5, True, 55), (2, 1.0, False, 55)]
    assert recorder.frames[2][4][0] == 2.0 and recorder.closed
    # the stage times by status: the two tracked frames' mean and the coasting one's, apart (across chunks)
    by = timing_by_status([sums])
    assert set(by) == {"tracking", "coasting"}
    assert by["tracking"]["detection"] == pytest.approx(250.0) and by["coasting"]["filtering"] == pytest.approx(125.0)
    assert by["tracking"]["simulation"] == pytest.approx(10.0)  # (0 + 20 ms) / 2
    assert sums["loop_wall_s"] > 0


@pytest.mark.parametrize("overlap", [False, True])
def test_an_error_in_a_frame_still_closes_the_recorder(tmp_path, overlap):
    recorder = FakeRecorder()
    with pytest.raises(RuntimeError, match="tracker failed"):
        run_frames(FakeTracker(fail_at=0.5), frames(), RunRows(str(tmp_path / "run"), 3), recorder, overlap=overlap)
    assert recorder.closed and len(recorder.frames) == 1


def test_with_overlap_the_next_frame_is_made_while_the_tracker_steps(tmp_path):
    """The tracker's step on frame k waits (at most 10 s) for the source to start making frame k + 1: with
    overlap every wait but the last is met, the steps ran on another thread than the source, and the recorder
    was called on the source's."""
    made = [threading.Event() for _ in range(4)]
    threads = {"source": threading.get_ident()}

    def source():
        for k in range(4):
            made[k].set()
            yield FrameInput(k, float(k), np.zeros((4, 4), np.uint8))

    class Waiting(FakeTracker):
        def step(self, t_s, image, window_px=None):
            threads["step"] = threading.get_ident()
            k = int(t_s)
            self.calls.append(k + 1 < 4 and made[k + 1].wait(timeout=10.0))
            return super().step(t_s, image)

    class Recorder(FakeRecorder):
        def log_frame(self, k, *args, **kw):
            threads.setdefault("recorded", set()).add(threading.get_ident())
            super().log_frame(k, *args, **kw)

    tracker, recorder = Waiting(), Recorder()
    run_frames(tracker, source(), RunRows(str(tmp_path / "run"), 4), recorder, overlap=True)
    assert [c for c in tracker.calls if isinstance(c, bool)] == [True, True, True, False]
    assert threads["step"] != threads["source"]
    # the estimates are recorded on the source's thread (beside the next step), every frame once, in order
    assert threads["recorded"] == {threads["source"]} and [f[0] for f in recorder.frames] == [0, 1, 2, 3]


def test_with_overlap_an_error_in_the_source_stops_the_loop_after_the_frame_in_hand(tmp_path):
    recorder = FakeRecorder()

    def failing():
        yield from frames(2, dark=())
        raise OSError("frame 2 unreadable")

    with pytest.raises(OSError, match="unreadable"):
        run_frames(FakeTracker(), failing(), RunRows(str(tmp_path / "run"), 3), recorder, overlap=True)
    assert recorder.closed and [f[0] for f in recorder.frames] == [0, 1]


def test_without_a_recorder_the_rows_are_still_filled(tmp_path):
    """Without a recorder (the runs after run 0 of `envisat run`), with a progress bar."""
    run_dir = str(tmp_path / "run")
    sums = run_frames(FakeTracker(), frames(dark=()), RunRows(run_dir, 3), progress="test frames")
    assert sums["frames_skipped_eclipse"] == 0
    assert np.load(os.path.join(run_dir, "x_hat.npy"))[:, 0].tolist() == [0.0, 0.5, 1.0]


def test_the_stage_times_by_status_count_every_frame_of_a_chunk(tmp_path):
    """Four tracked frames in one chunk, rendering 10, 20, 30 and 60 ms: summary.json's rendering ms per tracked
    frame is their mean, 30 ms (each frame added under its status, repeats within a chunk too)."""
    image = np.zeros((4, 4), np.uint8)
    frames = (FrameInput(k, float(k), image, (0.0, r, 0.0)) for k, r in enumerate((0.01, 0.02, 0.03, 0.06)))
    sums = run_frames(FakeTracker(), frames, RunRows(str(tmp_path / "run"), 4, chunk=4))
    by = timing_by_status([sums])
    assert set(by) == {"tracking"}
    assert by["tracking"]["rendering"] == pytest.approx(30.0) and by["tracking"]["detection"] == pytest.approx(250.0)


def test_the_recordings_line_for_a_lost_frame_says_why(tmp_path):
    """The recording's events: a line at each change of status, a loss with the tracker's own reason (its
    TrackEstimate's "lost: <why>"): a warm start on the upper stage (models/upper_stage_detector.safetensors,
    default scenario and seed, 20 s) is lost at its first frame by its windowed NIS (100 beyond 58, 16 dof: the
    detector's keypoints contradict even the exact truth there, NIS 97), and the line read "t = 0.0 s: lost"."""
    from envisat_pose.analysis.recording import TrackRecorder, read_recording
    from envisat_pose.geometry import load_camera

    why = "lost: innovations inconsistent: windowed NIS 100 beyond 58 (16 dof)"

    class Losing(FakeTracker):
        def step(self, t_s, image, window_px=None):
            est = super().step(t_s, image)
            if t_s == 0.0:
                return dataclasses.replace(est, status="lost", x_hat=np.full(12, np.nan), events=(why,))
            return dataclasses.replace(est, status="acquiring", x_hat=np.full(12, np.nan))

    path = tmp_path / "run.rrd"
    recorder = TrackRecorder(f"save:{path}", load_camera(), with_truth=False)
    run_frames(Losing(), frames(2, dark=()), RunRows(str(tmp_path / "run"), 2), recorder)
    events = read_recording(str(path))[1]["/events"]
    assert events["TextLog:text"] == [[f"t = 0.0 s: {why}"], ["t = 0.5 s: acquiring"]]
    assert events["TextLog:level"] == [["WARN"], ["INFO"]]
