"""The closed loop's camera frames (pipelines/runs/closed_loop.py): frame k of a run rendered by MuJoCo from the
truth and corrupted by the space camera with the frame's own noise, whole or, with RunConfig.render_window, the
tracker's window alone (windowed_frame), made while the tracker steps the frame before (frame_loop.run_frames'
overlap).

A window is planned from the tracker's state: frame k is made while the tracker steps frame k - 1, so its window
comes from the plan the tracker made right after frame k - 2 (PlanAhead: Tracker.planned_window two frames on),
grown by AHEAD_GROWTH of its side and AHEAD_PAD_PX on every side. Before the tracker steps frame k, the frame's
`ready` asks the tracker for its plan as it stands then; a frame whose window does not hold that plan's window is
made again for it (or whole, where the tracker now wants the whole frame): the tracker looks only at pixels made
for what it plans, as it would without the overlap.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field

import numpy as np

from envisat_pose.attitude import mrp_to_dcm
from envisat_pose.datagen.factory import draw_corruption_params, with_appearance
from envisat_pose.datagen.render_view import View
from envisat_pose.datagen.views import unit
from envisat_pose.pipelines.runs.frame_loop import FrameInput
from envisat_pose.state import MRP, POS

AHEAD_GROWTH = 0.02  # a window planned a frame early: grown by this share of its side on every side...
AHEAD_PAD_PX = 4  # ...and these pixels (the plans a frame apart: within 0.5 px, design.md)


class PlanAhead:
    """The tracker as the frame loop steps it (step(t_s, image)), plus, right after each step of frame k (on the
    loop's worker, the tracker idle), the window it plans for frame k + 2 (Tracker.planned_window; None: the whole
    frame). ahead[k]: frame k's, written once frame k - 2 is stepped, so reading it while frame k - 1 is stepped
    gives the same answer however the two threads run."""

    def __init__(self, tracker, t_s: np.ndarray):
        self.tracker, self.t_s = tracker, np.asarray(t_s, dtype=float)
        self.ahead: dict[int, np.ndarray | None] = {}

    def step(self, t_s: float, image, window_px: np.ndarray | None = None):
        est = self.tracker.step(t_s, image, window_px)
        k = int(np.searchsorted(self.t_s, t_s))
        if k + 2 < len(self.t_s):
            self.ahead[k + 2] = self.tracker.planned_window(float(self.t_s[k + 2]))
        self.ahead.pop(k, None)  # frame k was made (and its entry read) before this step began
        return est


def grown_window(window: np.ndarray) -> np.ndarray:
    """The window (x0, y0, side) px grown by AHEAD_GROWTH of its side plus AHEAD_PAD_PX on every side."""
    x0, y0, side = (int(v) for v in window)
    m = int(np.ceil(AHEAD_GROWTH * side)) + AHEAD_PAD_PX
    return np.array([x0 - m, y0 - m, side + 2 * m])


def window_holds(outer: np.ndarray, inner: np.ndarray) -> bool:
    """Whether the window outer (x0, y0, side) px holds the window inner whole."""
    (a, b, s), (x, y, t) = (tuple(int(v) for v in w) for w in (outer, inner))
    return a <= x and b <= y and x + t <= a + s and y + t <= b + s


@dataclass
class FrameMaker:
    """Makes a run's frames: its renderer (SceneRenderer), the image config (GenerateConfig), the run's seed and
    index (frame k's noise: SeedSequence(seed, spawn_key=(run, 1, k))), the appearance's seed, and per frame the
    sun and nadir in C (the Earth's shadow is closed_loop_frames' to skip). Counts the frames made as windows and
    those made again."""

    renderer: object
    gcfg: object
    seed: int
    run: int
    appearance_seed: int
    sun_C: np.ndarray
    nadir_C: np.ndarray
    counts: dict = field(default_factory=lambda: {"frames_windowed": 0, "frames_window_remade": 0})

    def image(self, k: int, x: np.ndarray, window: np.ndarray | None) -> tuple[np.ndarray, float, float]:
        """Frame k (state x (12,)) whole (window None) or the window alone: (image (n, n) uint8, s rendering,
        s camera)."""
        from envisat_pose.datagen.corrupt import apply_corruption

        t0 = time.perf_counter()
        g = self.gcfg
        view = View(x[POS], mrp_to_dcm(x[MRP]).T, self.sun_C[k], unit(self.nadir_C[k]),
                    float(np.linalg.norm(self.nadir_C[k])), earth_backdrop=g.earth_probability > 0)
        view, _ = with_appearance(g, view, {}, self.appearance_seed)
        rng = np.random.default_rng(np.random.SeedSequence(self.seed, spawn_key=(self.run, 1, k)))
        if window is not None:
            self.counts["frames_windowed"] += 1
            image, t_render, t_camera = windowed_frame(self.renderer, view, window, g, x, rng)
            return image, time.perf_counter() - t0 - t_camera, t_camera  # the view's set-up counted as rendering
        rendered = self.renderer.render(view, labels=False)  # the image and the pose: no depth or mask
        t_render = time.perf_counter() - t0
        t0 = time.perf_counter()
        params = draw_corruption_params(g, rendered, x, self.renderer.K[0, 0], self.renderer.target_boxes, rng)
        return apply_corruption(rendered.gray_u8, params), t_render, time.perf_counter() - t0

    def ready(self, frame: FrameInput, made: np.ndarray, tracker, x: np.ndarray):
        """frame's FrameInput.ready for a frame made as the window `made`: the frame itself when made holds the
        window the tracker plans now, else the frame made again for that plan (whole where it has none)."""

        def final() -> FrameInput:
            plan = tracker.planned_window(frame.t_s)
            if plan is not None and window_holds(made, plan):
                return dataclasses.replace(frame, ready=None)
            self.counts["frames_window_remade"] += 1
            image, t_render, t_camera = self.image(frame.k, x, plan)
            sim, r0, c0 = frame.stage_s
            return dataclasses.replace(frame, image=image, stage_s=(sim, r0 + t_render, c0 + t_camera), ready=None,
                                       window_px=plan)

        return final


def closed_loop_frames(maker: FrameMaker, t_s: np.ndarray, x_truth: np.ndarray, eclipse: np.ndarray,
                       sim_s_per_frame: float, plan_ahead: PlanAhead | None, full_frame_every: int, truth=None):
    """FrameInputs of a run: frame k rendered from x_truth[k] (None in the Earth's shadow: eclipse[k]); with a
    plan_ahead (RunConfig.render_window), the window it planned for frame k, grown (grown_window; the frame's
    window_px), except every full_frame_every-th frame, and checked by the frame's ready (FrameMaker.ready).
    truth: (corners_px (T, K, 2), in_frame (T, K)) for the recording, or None."""
    for k in range(len(t_s)):
        x = x_truth[k]
        image, t_render, t_camera, made = None, 0.0, 0.0, None
        if not eclipse[k]:
            if plan_ahead is not None and k % full_frame_every:
                planned = plan_ahead.ahead.get(k)
                made = None if planned is None else grown_window(planned)
            image, t_render, t_camera = maker.image(k, x, made)
        kw = {} if truth is None else {"x_true": x, "corners_true_px": truth[0][k], "in_frame": truth[1][k]}
        frame = FrameInput(k, float(t_s[k]), image, (sim_s_per_frame, t_render, t_camera), window_px=made, **kw)
        if made is not None:
            frame = dataclasses.replace(frame, ready=maker.ready(frame, made, plan_ahead.tracker, x))
        yield frame


def windowed_frame(renderer, view, window: np.ndarray, gcfg, x: np.ndarray, rng: np.random.Generator
                   ) -> tuple[np.ndarray, float, float]:
    """A frame of which only `window` (x0, y0, side) px is made: the space camera's parameters drawn first
    (draw_corruption_params from rng, as a full frame draws them, from the view's pose: SceneRenderer.view_pose),
    then MuJoCo renders the window grown by the camera's margin for them (corruption_margin_px;
    SceneRenderer.render_window), the camera corrupts it (datagen.corrupt.apply_corruption_window), and it is
    pasted into a black frame of the full size at its place. Returns (image (n, n) uint8, s rendering,
    s camera)."""
    from envisat_pose.datagen.corrupt import apply_corruption_window, corruption_margin_px

    t0 = time.perf_counter()
    n = renderer.resolution_px
    x0, y0, side = (int(v) for v in window)
    params = draw_corruption_params(gcfg, renderer.view_pose(view), x, renderer.K[0, 0], renderer.target_boxes, rng)
    m = corruption_margin_px(params)
    t_camera = time.perf_counter() - t0
    t0 = time.perf_counter()
    clean = renderer.render_window(view, (x0 - m, y0 - m, side + 2 * m)).gray_u8
    t_render = time.perf_counter() - t0
    t0 = time.perf_counter()
    win = apply_corruption_window(clean, (x0, y0, side), n, params)
    image = np.zeros((n, n), np.uint8)
    u0, v0, u1, v1 = max(x0, 0), max(y0, 0), min(x0 + side, n), min(y0 + side, n)
    if u1 > u0 and v1 > v0:
        image[v0:v1, u0:u1] = win[v0 - y0:v1 - y0, u0 - x0:u1 - x0]
    return image, t_render, t_camera + time.perf_counter() - t0
