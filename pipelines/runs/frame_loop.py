"""The per-frame loop of `envisat run` (pipelines/runs/closed_loop.py) and `envisat track` (pipelines/runs/track.py): each
frame's input (FrameInput: the image or None, the stage times before the tracker, a truth for the recording) goes
through the Tracker, its estimate into the run's row (rows.store_estimate into a RunRows), the recorder (where there
is one) and the row's stage times (rows.STAGES, by name); a progress bar shows the tracker's status. The callers
differ only in where the frames come from: a generator of FrameInput."""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Iterable

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
    x_true (12,), corners_true_px (8, 2) and in_frame (8,) bool (None without)."""

    k: int
    t_s: float
    image: np.ndarray | None
    stage_s: tuple = NO_STAGE_TIMES
    x_true: np.ndarray | None = None
    corners_true_px: np.ndarray | None = None
    in_frame: np.ndarray | None = None


def run_frames(tracker, frames: Iterable[FrameInput], rows, recorder=None, jpeg_quality: int = 80,
               progress: str | None = None) -> dict:
    """Step the tracker over frames (in order, k = 0, 1, ...), storing each estimate into rows (a RunRows) with
    the frame's stage times (s, STAGES' order), logging it to recorder (a TrackRecorder, or None) with the image
    at jpeg_quality; progress: the bar's description (None: no bar). The bar and the recorder are closed
    whatever happens; returns rows.close(), the run's reductions."""
    bar = None
    if progress is not None:
        from tqdm import tqdm

        bar = tqdm(total=rows.T, unit="frame", desc=progress, mininterval=0.5)
    try:
        for f in frames:
            est = tracker.step(f.t_s, f.image)
            i, out = rows.row(f.k), rows.buf
            store_estimate(out, i, est)
            out["skipped"][i] = f.image is None
            t0 = time.perf_counter()
            if recorder is not None:
                recorder.log_frame(f.k, est_row(out, i, f.t_s), f.image, jpeg_quality, x_true=f.x_true,
                                   corners_true_px=f.corners_true_px, in_frame=f.in_frame)
            timing = out["timing_s"][i]
            timing[:DETECTION] = f.stage_s
            timing[DETECTION] = est.timing_s.get("detection", 0.0)
            timing[FILTERING] = est.timing_s.get("filtering", 0.0)
            timing[RECORDING] = time.perf_counter() - t0
            if bar is not None:
                bar.update(1)
                bar.set_postfix_str(est.status, refresh=False)
    finally:
        if bar is not None:
            bar.close()
        if recorder is not None:
            recorder.close()
    return rows.close()
