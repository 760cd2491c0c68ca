"""The closed loop with the rotation chart of the sigma points (`[filter] sigma_chart = "rotation"`,
filtering.ukf.chart_retract): it runs, it scores NEES in the chart its filter's covariance is in (est.npz's P, the
recording's NEES line), and, on ENVISAT with detections from the truth plus noise, it claims no frame while wrong.

The detector is a stand-in (as tests/pipelines/runs/test_window_target.py's): it names the MuJoCo truth's visible
corners of the frame the tracker steps (the frame time gives the index; nothing else of the truth reaches the
tracker) with Gaussian pixel noise drawn per frame. 60 s of 256-px frames, default scenario, seed 3."""

import json

import numpy as np
import pytest

from envisat_pose.filtering.ukf import chart_error, state_residual
from envisat_pose.geometry import load_camera
from envisat_pose.perception.detect import FrameDetection
from envisat_pose.pipelines.jobs import resolve_job
from envisat_pose.pipelines.runs import closed_loop
from envisat_pose.pipelines.runs.scoring import scored_masks
from envisat_pose.pipelines.tracking import acquisition as acq
from envisat_pose.pipelines.tracking.tracker import Tracker

RES = 256  # px, square frames
SIGMA_PX = 0.2  # at 256 px: 0.8 px at the MJCF camera's 1024


class NoisyTruthDetector:
    """Names the truth's visible corners of frame `k` (set before each step) with noise, at the frames' size."""

    def __init__(self, truth, resolution_px: int):
        self.truth, self.k = truth, 0
        self.uv = closed_loop.rescale_px(truth.corners_px, load_camera(), closed_loop.run_camera(resolution_px))

    def detect(self, image, K, roi_px=None, **priors):
        k = self.k
        vis = self.truth.visible[k] & self.truth.in_frame[k]
        rng = np.random.default_rng(k)
        z = np.where(vis[:, None], self.uv[k] + rng.normal(0.0, SIGMA_PX, (8, 2)), np.nan)
        cov = np.where(vis[:, None, None], np.eye(2) * SIGMA_PX ** 2, np.nan)
        return FrameDetection(z, cov, vis * 0.9, vis, z[acq.half_turn()[0]], 0.3, False,
                              np.array([0.0, 0.0, float(image.shape[0])]), z[vis])


@pytest.fixture(scope="module")
def rotation_run(tmp_path_factory):
    """The loop's outputs (summary, est.npz's arrays, the recording's NEES series) with sigma_chart 'rotation'."""
    from envisat_pose.analysis.recording import read_recording

    mp = pytest.MonkeyPatch()
    cfg = resolve_job("run", "default", overrides={"duration_s": 60.0, "seed": 3, "workers": 1,
                                                   "image.resolution_px": RES, "filter.sigma_chart": "rotation"})
    assert cfg.filter.sigma_chart == "rotation"
    det = NoisyTruthDetector(closed_loop.run_truth(cfg), RES)
    step = Tracker.step

    def stepping(self, t_s, image, window_px=None):
        det.k = int(round(t_s * cfg.rate_hz))
        return step(self, t_s, image, window_px)

    mp.setattr(Tracker, "step", stepping)
    mp.setattr(closed_loop, "tracker_detector", lambda *a, **kw: det)
    out = tmp_path_factory.mktemp("rotation_loop")
    try:
        closed_loop.run_closed_loop(cfg, str(out), progress=False)
    finally:
        mp.undo()
    summary = json.loads((out / "summary.json").read_text())
    with np.load(out / "est.npz") as z:
        est = {k: z[k] for k in ("x_true", "x_hat", "P", "status", "config_json")}
    _, temporal = read_recording(str(out / "recording.rrd"))
    nees_rec = temporal["/metrics/nees/value"]
    return summary, est, nees_rec


def test_the_loop_takes_the_rotation_chart_and_scores_nees_in_it(rotation_run):
    """The summary's mean NEES is est.npz's P read with the chart's error (filtering.ukf.chart_error, 'rotation'),
    over the scored frames; the additive chart's error (state_residual) gives another number. The recording's NEES
    line is the chart's too, frame by frame."""
    summary, est, nees_rec = rotation_run
    assert json.loads(str(est["config_json"]))["run"]["filter"]["sigma_chart"] == "rotation"
    scores = summary["scores"]
    mask = scored_masks(est["status"])[0]
    assert mask.sum() >= 20
    x_true, x_hat, P = est["x_true"][0][mask], est["x_hat"][0][mask], est["P"][0][mask]

    def mean_nees(e):
        return float(np.mean(np.einsum("ti,ti->t", e, np.linalg.solve(P, e[..., None])[..., 0])))

    chart = mean_nees(chart_error(x_true, x_hat, "rotation"))
    additive = mean_nees(-state_residual(x_true.copy(), x_hat))
    assert scores["scored"]["mean_nees"] == pytest.approx(chart, rel=1e-9)
    assert abs(additive - chart) > 1e-6 * chart, (additive, chart)  # the charts' NEES differ: the test can tell
    # the recording's NEES line: frame by frame the chart's (the frames it logs are those with an estimate)
    frames = np.asarray(nees_rec["frame"])
    logged = np.array([float(np.ravel(v)[0]) for v in nees_rec["Scalars:scalars"]])
    k = np.flatnonzero(mask)
    at = np.isin(frames, k)
    e = chart_error(est["x_true"][0][frames[at]], est["x_hat"][0][frames[at]], "rotation")
    P_at = est["P"][0][frames[at]]
    want = np.einsum("ti,ti->t", e, np.linalg.solve(P_at, e[..., None])[..., 0])
    np.testing.assert_allclose(logged[at], want, rtol=1e-6)


def test_the_rotation_charts_loop_on_envisat_claims_no_frame_while_wrong(rotation_run):
    """Truth-plus-noise corners, cold start: the first track is correct, no frame is claimed while wrong, and the
    chart's NEES is that of a consistent filter (12 expected; the stand-in's white noise)."""
    scores = rotation_run[0]["scores"]
    assert scores["runs_tracked"] == 1 and scores["first_track_correct"] == 1
    assert scores["false_lock_s"] == 0.0
    assert 3.0 < scores["scored"]["mean_nees"] < 30.0, scores["scored"]["mean_nees"]
