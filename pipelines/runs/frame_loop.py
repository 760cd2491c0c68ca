"""The per-frame loop of `envisat run` (pipelines/runs/closed_loop.py) and `envisat track` (pipelines/runs/track.py): each
frame's input (FrameInput: the image or None, the stage times before the tracker, a truth for the recording) goes
through the Tracker, its estimate into the run's row (rows.store_estimate into a RunRows), the recorder (where there
is one) and the row's stage times (rows.STAGES, by name); a progress bar shows the tracker's status. The callers
differ only in where the frames come from: a generator of FrameInput."""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Callable, Iterable

import numpy as np

from envisat_pose.pipelines.runs.rows import STAGES, est_row, store_estimate

STAGE_INDEX = {name: i for i, name in enumerate(STAGES)}  # a stage's column in the rows' timing_s
# the tracker times detection and filtering (its TrackEstimate.timing_s, by those names), the loop the recording;
# the stages before them are timed by whoever makes the frame (FrameInput.stage_s)
DETECTION, FILTERING, RECORDING = STAGE_INDEX["detection"], STAGE_INDEX["filtering"], STAGE_INDEX["recording"]
BEFORE_TRACKER = STAGES[:DETECTION]
NO_STAGE_TIMES = (0.0,) * len(BEFORE_TRACKER)  # frames read, not made (`envisat track`)


@dataclass(frozen=True)
class FrameInput:
    """Frame k at t_s (s): image (H, W) uint8, or None where there is no frame (the tracker predicts); stage_s:
    the seconds of BEFORE_TRACKER (simulation, rendering, camera) spent on it; with a truth for the recording,
    x_true (12,), corners_true_px (8, 2) and in_frame (8,) bool (None without). window_px: (x0, y0, side) px where
    only that window of the image was made (the rest black: Tracker.step's window_px), None for a whole frame.
    ready: for a frame made ahead of the tracker (run_frames' overlap), called on the maker's thread once the
    tracker has stepped every earlier frame and before it steps this one; returns the frame to step (this one, or
    one remade for the tracker as it stands then). None: the frame is final as made."""

    k: int
    t_s: float
    image: np.ndarray | None
    stage_s: tuple = NO_STAGE_TIMES
    x_true: np.ndarray | None = None
    corners_true_px: np.ndarray | None = None
    in_frame: np.ndarray | None = None
    ready: Callable[[], "FrameInput"] | None = None
    window_px: np.ndarray | None = None

    def final(self) -> "FrameInput":
        """The frame to step: ready()'s where there is one."""
        return self if self.ready is None else self.ready()


def run_frames(tracker, frames: Iterable[FrameInput], rows, recorder=None, jpeg_quality: int = 80,
               progress: str | None = None, overlap: bool = False, tally=None) -> dict:
    """Step the tracker over frames (in order, k = 0, 1, ...), storing each estimate into rows (a RunRows) with
    the frame's stage times (s, STAGES' order), logging it to recorder (a TrackRecorder, or None) with the image
    at jpeg_quality; progress: the bar's description (None: no bar). tally: where the frames done are counted
    for a bar elsewhere (a run_progress.FrameTally: advance() per frame), or None. The bar, the tally and the
    recorder are closed whatever happens; returns rows.close(), the run's reductions, with loop_wall_s: the
    loop's wall time (s).

    overlap: the caller's generator makes frame k+1 (rendering, the camera, reading a file: on this thread, where
    its GL context lives) while one worker thread steps the tracker on frame k (torch, OpenCV, MuJoCo's renderer
    and numpy's large operations release the GIL, so the two share the cores); frame k's estimate is stored
    and recorded here, beside the worker's step of frame k+1. A frame made for the tracker's state (the closed
    loop's rendered window) is made for its state a step earlier and checked by its FrameInput.ready; frames that
    depend on nothing reach the tracker as without overlap, so every estimate is the same. The stages' times
    then overlap and sum to more than the wall time."""
    bar = None
    if progress is not None:
        from tqdm import tqdm

        bar = tqdm(total=rows.T, unit="frame", desc=progress, mininterval=0.5)

    def track(f: FrameInput):
        return tracker.step(f.t_s, f.image, f.window_px)

    def store(f: FrameInput, est) -> int:
        i, out = rows.row(f.k), rows.buf
        store_estimate(out, i, est)
        out["skipped"][i] = f.image is None
        timing = out["timing_s"][i]
        timing[:DETECTION] = f.stage_s
        timing[DETECTION] = est.timing_s.get("detection", 0.0)
        timing[FILTERING] = est.timing_s.get("filtering", 0.0)
        return i

    def record(f: FrameInput, est, i: int) -> None:  # before the next store: row i is still in rows.buf
        t0 = time.perf_counter()
        if recorder is not None:
            # the tracker's events beside the row: the recording's line at a change of status says why (lost: ...)
            recorder.log_frame(f.k, est_row(rows.buf, i, f.t_s) | {"events": est.events}, f.image, jpeg_quality,
                               x_true=f.x_true, corners_true_px=f.corners_true_px, in_frame=f.in_frame)
        rows.buf["timing_s"][i][RECORDING] = time.perf_counter() - t0
        if bar is not None:
            bar.update(1)
            bar.set_postfix_str(est.status, refresh=False)
        if tally is not None:
            tally.advance()

    wall0 = time.perf_counter()
    try:
        if overlap:
            _overlapped(track, store, record, frames)
        else:
            for f in frames:
                f = f.final()
                est = track(f)
                record(f, est, store(f, est))
    finally:
        if bar is not None:
            bar.close()
        if tally is not None:
            tally.close()
        if recorder is not None:
            recorder.close()
    loop_wall_s = time.perf_counter() - wall0
    return {**rows.close(), "loop_wall_s": loop_wall_s}


def _overlapped(track, store, record, frames: Iterable[FrameInput]) -> None:
    """track(f) for every frame in order on one worker thread, at most one frame ahead: the next frame is made
    here while the worker tracks the last, and made final (FrameInput.final) here between the two steps; each
    estimate is stored here as soon as it is done (store(f, est) -> its row), then recorded (record(f, est, row))
    while the worker tracks the next frame. An error on either side stops both after the frame in hand (the
    worker's is raised here)."""
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="tracker") as pool:
        pending = None  # (frame, future of its estimate)
        try:
            for f in frames:  # making frame k here while the worker is on frame k - 1
                done = None
                if pending is not None:
                    (last, fut), pending = pending, None
                    est = fut.result()
                    done = (last, est, store(last, est))
                f = f.final()  # here: the tracker is idle, GL on this thread
                pending = (f, pool.submit(track, f))
                if done is not None:
                    record(*done)
        finally:  # the frame in hand: stored and recorded (an error here or the worker's raised after it)
            if pending is not None:
                (last, fut), pending = pending, None
                est = fut.result()
                record(last, est, store(last, est))
