"""A campaign whose first measured steps do not fix the target's pose says so (pipelines/campaigns/
observability.py): the rule (three or more measured keypoints off one line) against a brute-force computation, and
`estimate` / `montecarlo` on a rod that shows two keypoints near its axis for its first ~114 s (seed 0), against
the same rod seen from a start with more keypoints in view (seed 1), which says nothing."""

import itertools
import warnings

import numpy as np
import pytest

from envisat_pose.filtering.measurements import pose_fixed
from envisat_pose.filtering.montecarlo import MeasurementConfig
from envisat_pose.pipelines.campaigns.observability import unfixed_start, warn_if_unfixed_start

# a 30 m rod: two tips on its axis, a fin near one end, a point 0.1 m off the axis at the middle (a tester's file)
ROD_XML = """<mujoco model="rod">
  <worldbody>
    <body name="target">
      <inertial pos="0 0 0" mass="200" fullinertia="1.0 15000 15000 0 0 0"/>
      <geom name="rod" type="capsule" fromto="-15 0 0 15 0 0" size="0.1"/>
      <geom name="fin" type="box" pos="14 0 0.3" size="0.5 0.02 0.3"/>
      <site name="kp_tip_p" pos="15.1 0 0"/>
      <site name="kp_tip_m" pos="-15.1 0 0"/>
      <site name="kp_fin_top" pos="14.5 0 0.6"/>
      <site name="kp_fin_bot" pos="13.5 0 0.6"/>
      <site name="kp_mid" pos="0 0 0.1"/>
    </body>
  </worldbody>
</mujoco>
"""


def brute_force_fixed(points: np.ndarray, tol: float) -> bool:
    """Some three of the points span a triangle whose area is more than tol of the points' extent squared."""
    extent = max((np.linalg.norm(a - b) for a, b in itertools.combinations(points, 2)), default=0.0)
    return any(0.5 * np.linalg.norm(np.cross(b - a, c - a)) > tol * extent**2
               for a, b, c in itertools.combinations(points, 3))


def test_the_pose_is_fixed_by_three_keypoints_off_one_line_only():
    rng = np.random.default_rng(5)
    kp = rng.normal(size=(6, 3)) * [10.0, 2.0, 1.0]
    line = np.outer(np.linspace(-1, 1, 6), [3.0, -1.0, 2.0]) + 1e-9 * rng.normal(size=(6, 3))
    masks = np.array([[1, 1, 0, 0, 0, 0], [1, 1, 1, 0, 0, 0], [0, 0, 1, 1, 1, 1], [0] * 6, [1] * 6], bool)
    for points in (kp, line):
        got = pose_fixed(points, masks)
        want = [brute_force_fixed(points[m], 1e-4) for m in masks]
        assert got.tolist() == want
    assert pose_fixed(kp, masks).tolist() == [False, True, True, False, True]  # two points never fix it


def test_the_steps_before_the_first_fixed_one_are_counted_and_warned():
    kp = np.array([[0, 0, 0], [10, 0, 0], [5, 3, 0], [5, 0, 2]], float)
    t_s = np.arange(10.0)
    base = np.zeros((10, 4), bool)
    base[1:5, :2] = True  # t = 1-4 s: two keypoints
    base[5:, :] = True  # t = 5 s on: all four
    mcfg = MeasurementConfig()
    assert unfixed_start(t_s, kp, base, mcfg) == (4, 5.0)
    with pytest.warns(UserWarning, match=r"only from t = 5 s: 4 step\(s\) before"):
        warn_if_unfixed_start(t_s, kp, base, mcfg)
    assert unfixed_start(t_s, kp, base, MeasurementConfig(max_markers=2)) == (9, None)  # two markers: never
    assert unfixed_start(t_s, kp, base, MeasurementConfig(outages_s=((0.5, 4.5),))) == (0, 5.0)  # outage: no update
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        warn_if_unfixed_start(t_s[:5], kp, base[5:], mcfg)  # all four from the first measured step: none


def test_pixels_need_four_keypoints_as_the_filter_does_markers_three():
    """Three pixels leave P3P's up to four poses; the filter's rule (POSE_CORNERS) waits for four, and the warning
    counted three for any kind (its first fixed step one frame early)."""
    kp = np.array([[0, 0, 0], [10, 0, 0], [5, 3, 0], [5, 0, 2]], float)
    t_s = np.arange(10.0)
    base = np.zeros((10, 4), bool)
    base[1:5, :3] = True  # t = 1-4 s: three keypoints off one line
    base[5:, :] = True  # t = 5 s on: all four
    assert unfixed_start(t_s, kp, base, MeasurementConfig(kind="markers3d")) == (0, 1.0)
    assert unfixed_start(t_s, kp, base, MeasurementConfig(kind="pixels+range")) == (0, 1.0)
    assert unfixed_start(t_s, kp, base, MeasurementConfig(kind="pixels")) == (4, 5.0)
    with pytest.warns(UserWarning, match=r"only from t = 5 s: 4 step\(s\) before measure fewer than 4 keypoints"):
        warn_if_unfixed_start(t_s, kp, base, MeasurementConfig(kind="pixels"))


def _said(record) -> list[str]:
    return [str(w.message) for w in record if "fix the target's pose" in str(w.message)]


def test_estimate_and_montecarlo_warn_on_a_rod_seen_along_its_axis(tmp_path):
    from envisat_pose.datagen.scenario import ScenarioConfig
    from envisat_pose.pipelines.campaigns.campaign import MonteCarloConfig, run_campaign
    from envisat_pose.pipelines.campaigns.estimate import EstimateConfig, run_estimate
    from envisat_pose.pipelines.campaigns.simulate import run_simulate
    from envisat_pose.pipelines.jobs import resolve_job

    rod = tmp_path / "rod.xml"
    rod.write_text(ROD_XML)
    said = {}
    for seed in (0, 1):
        scen = resolve_job("simulate", "default", None, {"duration_s": 120.0, "seed": seed, "target.file": str(rod)})
        assert isinstance(scen, ScenarioConfig)
        truth = tmp_path / f"rod{seed}.npz"
        run_simulate(scen, truth)
        with warnings.catch_warnings(record=True) as rec:
            warnings.simplefilter("always")
            run_estimate(EstimateConfig(runs=1, seed=seed), tmp_path / f"est{seed}.npz", truth_path=truth)
        said[seed] = _said(rec)
    assert len(said[0]) == 1 and "only from t = 114 s" in said[0][0], said[0]
    assert said[1] == []
    with warnings.catch_warnings(record=True) as rec:
        warnings.simplefilter("always")
        run_campaign(MonteCarloConfig(runs=2, duration_s=120.0, settle_s=100.0, seed=0, target=str(rod)),
                     tmp_path / "mc")
    assert len(_said(rec)) == 1
