"""The closed loop's frames made a step ahead (pipelines/runs/loop_frames.py), with a fake tracker and frame maker:
the window planned two frames on, grown; a frame whose window does not hold the tracker's plan when it is stepped
is made again for that plan (whole where the tracker has none); full frames at the set interval and none in
the Earth's shadow; and a run through run_frames' overlap steps every frame on what was planned for it."""

import numpy as np

from envisat_pose.pipelines.runs.frame_loop import run_frames
from envisat_pose.pipelines.runs.loop_frames import (
    AHEAD_GROWTH,
    AHEAD_PAD_PX,
    FrameMaker,
    PlanAhead,
    closed_loop_frames,
    grown_window,
    window_holds,
)
from envisat_pose.pipelines.runs.rows import RunRows
from envisat_pose.pipelines.tracking.tracker import TrackEstimate

N = 64  # the fake frames' side


def test_grown_window_and_holds():
    w = np.array([100, 200, 50])
    m = int(np.ceil(AHEAD_GROWTH * 50)) + AHEAD_PAD_PX
    assert grown_window(w).tolist() == [100 - m, 200 - m, 50 + 2 * m]
    assert window_holds(grown_window(w), w) and window_holds(w, w)
    assert not window_holds(w, np.array([99, 200, 50])) and not window_holds(w, np.array([100, 200, 51]))
    assert not window_holds(w, np.array([130, 200, 30]))  # past the right edge


class PlanTracker:
    """Steps record (t_s, the image's marker: its [0, 0] pixel, or None) and the window_px given (windows);
    planned_window(t) is plans[(t, steps done)] (None where missing): what the tracker would plan for frame t after
    that many steps."""

    def __init__(self, plans):
        self.plans, self.steps, self.windows, self.K = plans, [], [], 8

    def planned_window(self, t_s):
        w = self.plans.get((float(t_s), len(self.steps)))
        return None if w is None else np.array(w)

    def step(self, t_s, image, window_px=None):
        self.steps.append((t_s, None if image is None else int(image[0, 0])))
        self.windows.append(None if window_px is None else tuple(int(v) for v in window_px))
        return TrackEstimate(t_s=t_s, status="tracking", x_hat=np.zeros(12), P=np.eye(12),
                             hypotheses=np.zeros((1, 12)), probabilities=np.ones(1), detection=None, naming=0,
                             measured=np.zeros(8, bool), rejected=np.zeros(8, bool), nis=0.0, nis_dof=0,
                             roi_px=None, converged=True, timing_s={})


class MarkerMaker(FrameMaker):
    """Frames marked by how they were made: [0, 0] = 1 whole, else 2 + the window's side (the windows asked for)."""

    def __init__(self):
        super().__init__(None, None, 0, 0, 0, None, None)
        self.asked = []

    def image(self, k, x, window):
        self.asked.append((k, None if window is None else tuple(int(v) for v in window)))
        if window is not None:
            self.counts["frames_windowed"] += 1
        image = np.zeros((N, N), np.uint8)
        image[0, 0] = 1 if window is None else 2 + int(window[2])
        return image, 0.0, 0.0


def frames_of(maker, tracker, T, eclipse=(), every=100):
    t_s = np.arange(T, dtype=float)
    ahead = PlanAhead(tracker, t_s)
    dark = np.array([k in eclipse for k in range(T)])
    return ahead, closed_loop_frames(maker, t_s, np.zeros((T, 12)), dark, 0.0, ahead, every)


def test_plan_ahead_plans_two_frames_on_after_each_step():
    # after 1 step (frame 0) the plan for frame 2; after 2 steps the plan for frame 3
    tracker = PlanTracker({(2.0, 1): (10, 10, 20), (3.0, 2): (11, 11, 21)})
    ahead = PlanAhead(tracker, np.arange(5, dtype=float))
    ahead.step(0.0, None)
    assert ahead.ahead[2].tolist() == [10, 10, 20] and set(ahead.ahead) == {2}
    ahead.step(1.0, None)
    assert ahead.ahead[3].tolist() == [11, 11, 21] and set(ahead.ahead) == {2, 3}
    ahead.step(2.0, None)
    assert set(ahead.ahead) == {3, 4}  # frame 1's entry dropped once read; frame 4's plan None
    assert ahead.ahead[4] is None


def test_a_window_that_holds_the_plan_is_kept_and_one_that_does_not_is_made_again():
    early, now_inside, now_outside = (20, 20, 10), (21, 21, 10), (0, 0, 10)
    plans = {(2.0, 1): early, (3.0, 2): early, (2.0, 2): now_inside, (3.0, 3): now_outside, (4.0, 3): None}
    tracker, maker = PlanTracker(plans), MarkerMaker()
    ahead, frames = frames_of(maker, tracker, 4)
    for f in frames:  # as run_frames without overlap: step each frame once final
        final = f.final()
        ahead.step(final.t_s, final.image, final.window_px)
    g = tuple(int(v) for v in grown_window(np.array(early)))
    # frames 0 and 1 whole (nothing planned yet); 2 as the grown early window, kept; 3 made again for the plan
    assert maker.asked == [(0, None), (1, None), (2, g), (3, g), (3, now_outside)]
    assert [m for _, m in tracker.steps] == [1, 1, 2 + g[2], 2 + now_outside[2]]
    assert tracker.windows == [None, None, g, now_outside]  # the tracker told which pixels were made
    assert maker.counts == {"frames_windowed": 3, "frames_window_remade": 1}


def test_a_window_is_made_whole_again_when_the_tracker_wants_the_whole_frame():
    plans = {(2.0, 1): (20, 20, 10)}  # after frame 1 the tracker plans nothing for frame 2 (lost, fell short)
    tracker, maker = PlanTracker(plans), MarkerMaker()
    ahead, frames = frames_of(maker, tracker, 3)
    for f in frames:
        final = f.final()
        ahead.step(final.t_s, final.image, final.window_px)
    assert maker.asked[-1] == (2, None) and tracker.steps[-1] == (2.0, 1)
    assert tracker.windows[-1] is None
    assert maker.counts["frames_window_remade"] == 1


def test_full_frames_at_the_interval_and_none_in_the_shadow():
    plans = {(float(k), k - 1): (20, 20, 10) for k in range(2, 8)}
    plans |= {(float(k), k): (20, 20, 10) for k in range(2, 8)}
    tracker, maker = PlanTracker(plans), MarkerMaker()
    ahead, frames = frames_of(maker, tracker, 8, eclipse=(5,), every=3)
    for f in frames:
        ahead.step(f.t_s, f.final().image)
    made = dict(maker.asked)
    assert made[3] is None and made[6] is None  # every third frame whole
    assert made[2] is not None and made[4] is not None and made[7] is not None
    assert 5 not in made and tracker.steps[5] == (5.0, None)


def test_overlapped_the_tracker_steps_each_frame_on_what_was_planned_for_it(tmp_path):
    """Through run_frames' overlap: the same steps as one after the other, whatever the threads' timing."""
    plans = {(float(k), n): (20 + n, 20, 10) for k in range(2, 12) for n in (k - 2, k - 1, k)}
    seq_tracker, seq_maker = PlanTracker(plans), MarkerMaker()
    ahead, frames = frames_of(seq_maker, seq_tracker, 12)
    for f in frames:
        ahead.step(f.t_s, f.final().image)
    tracker, maker = PlanTracker(plans), MarkerMaker()
    ahead, frames = frames_of(maker, tracker, 12)
    run_frames(ahead, frames, RunRows(str(tmp_path / "run"), 12), overlap=True)
    assert tracker.steps == seq_tracker.steps and maker.asked == seq_maker.asked
    made = {k: w for k, w in maker.asked}  # the last made of each frame
    assert tracker.windows == [made[k] for k in range(12)]
    assert maker.counts["frames_windowed"] >= 10


def test_overlapped_a_window_planned_early_that_misses_the_plan_is_made_again(tmp_path):
    """Through run_frames' overlap (as `envisat run` always steps): the plans move 40 px a step, so the window
    planned two frames on never holds the plan the tracker has when it steps the frame; each windowed frame is
    made again and the tracker steps the window it planned then (plans[(k, k)]), never the early one."""
    plans = {(float(k), n): (20 + 40 * n, 20, 10) for k in range(2, 8) for n in (k - 2, k - 1, k)}
    tracker, maker = PlanTracker(plans), MarkerMaker()
    ahead, frames = frames_of(maker, tracker, 8)
    run_frames(ahead, frames, RunRows(str(tmp_path / "run"), 8), overlap=True)
    assert tracker.windows == [None, None] + [plans[(float(k), k)] for k in range(2, 8)]
    assert [m for _, m in tracker.steps] == [1, 1] + [2 + 10] * 6  # the plan's side, not the grown window's
    assert maker.counts["frames_window_remade"] == 6


class TimedMaker(MarkerMaker):
    """MarkerMaker whose every make takes 0.25 s of rendering and 0.125 s of camera (as stage times)."""

    def image(self, k, x, window):
        return super().image(k, x, window)[0], 0.25, 0.125


def test_a_frame_made_again_counts_both_makes_in_its_stage_times():
    """The stage times of a frame made twice (a window, then again for the tracker's plan) are the two makes'
    sums: the time spent on that frame, which summary.json's ms per frame reports."""
    plans = {(2.0, 1): (20, 20, 10), (2.0, 2): (0, 0, 10)}
    tracker, maker = PlanTracker(plans), TimedMaker()
    ahead, frames = frames_of(maker, tracker, 3)
    stage = []
    for f in frames:
        final = f.final()
        stage.append(final.stage_s)
        ahead.step(final.t_s, final.image, final.window_px)
    assert maker.counts["frames_window_remade"] == 1 and tracker.windows[2] == (0, 0, 10)
    assert stage[1] == (0.0, 0.25, 0.125)  # made once
    assert stage[2] == (0.0, 0.5, 0.25)  # made twice
