"""A recording's titles say what the target's keypoints are: ENVISAT's "corners" (A-H), another target's
"keypoints" out of its own K. A CubeSat's truth recording titled its count plot "visible / in-frame corners", its
camera "camera (corners)", its legend "visible_corners"; its samples "image and corners"."""

import os
import sys

import rerun.blueprint as rrb

from envisat_pose.analysis import recording
from envisat_pose.analysis.recording import read_recording
from envisat_pose.analysis.recording_layout import estimate_blueprint, samples_blueprint, truth_blueprint
from envisat_pose.target import load_target

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))  # the folder's own helpers
from test_recording_blueprint import estimates, time_series_views  # noqa: E402

CUBESAT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", "models", "cubesat_3u.xml")


def view_names(blueprint: rrb.Blueprint) -> list[str]:
    """Every view's title in the blueprint."""
    names = []

    def walk(c):
        for x in getattr(c, "contents", []):
            if isinstance(x, rrb.View):
                names.append(x.name)
            elif hasattr(x, "contents"):
                walk(x)

    walk(blueprint.root_container)
    return names


def test_a_truth_recording_of_another_target_counts_its_keypoints(tmp_path):
    from envisat_pose.datagen.scenario import scenario_config
    from envisat_pose.datagen.truth import simulate_truth

    cubesat = load_target(CUBESAT)
    truth = simulate_truth(scenario_config("default", duration_s=4.0, target={"file": CUBESAT}))
    path = tmp_path / "truth.rrd"
    recording.write_truth_recording(str(path), truth, cubesat)
    assert set(time_series_views(path)) == {"range (m)", f"visible / in-frame keypoints (of {cubesat.num_keypoints})"}
    static, _ = read_recording(str(path))
    assert static["/metrics/visible_keypoints"]["SeriesLines:names"] == ["visible keypoints"]
    assert static["/metrics/in_frame_keypoints"]["SeriesLines:names"] == ["in-frame keypoints"]
    # an estimate of that truth: its plots' legends say so too
    recording.write_estimates_recording(str(tmp_path / "est.rrd"), estimates(T=3), truth, target=cubesat)
    assert read_recording(str(tmp_path / "est.rrd"))[0]["/metrics/visible_keypoints"]["SeriesLines:names"] == [
        "visible keypoints"]


def test_every_view_title_names_another_targets_keypoints_and_envisats_corners():
    cubesat = load_target(CUBESAT)
    for make in (truth_blueprint, estimate_blueprint, samples_blueprint):
        other, envisat = " | ".join(view_names(make(cubesat))), " | ".join(view_names(make()))
        assert "corners" not in other and "keypoints" in other, (make.__name__, other)
        assert "keypoints" not in envisat and "corners" in envisat, (make.__name__, envisat)
    assert "visible / in-frame corners" in view_names(truth_blueprint())
