"""`envisat run --target FILE.xml` (issue 56): the closed loop of another target, MuJoCo rendering that target and
the tracker following it with its keypoint detector; the weights refused in one line, nothing written, where they
cannot serve (none given where none ships beside the target file, ENVISAT's for another target, another target's,
never calibrated). The network here is untrained (the plumbing: the frames, the rows of K keypoints, the files);
tracking accuracy is the tracker's tests' (tests/pipelines/tracking/test_tracker_target.py) and the benchmarks'."""

import json
import os
import sys

import numpy as np
import pytest

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))  # the folder's own helpers
sys.path.insert(0, os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "perception"))
from keypoint_cases import untrained_weights  # noqa: E402
from refusals import refused  # noqa: E402

from envisat_pose.app.cli import main
from envisat_pose.datagen.target_scene import size_ratio
from envisat_pose.target import load_target

# the repository's models folder, by this file's place: the tests run from any working folder
MODELS = os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))), "models")
UPPER = os.path.join(MODELS, "upper_stage.xml")


@pytest.fixture(scope="module")
def weights(tmp_path_factory):
    folder = tmp_path_factory.mktemp("run_target")
    return {"upper": untrained_weights(folder / "upper.safetensors", UPPER, sigma_px=1.5),
            "uncalibrated": untrained_weights(folder / "uncal.safetensors", UPPER),
            "cubesat": untrained_weights(folder / "cubesat.safetensors", os.path.join(MODELS, "cubesat_3u.xml"), 1.5)}


def test_the_closed_loop_of_another_target_writes_its_keypoints(weights, tmp_path, capsys):
    out = tmp_path / "run"
    assert main(["run", "--target", UPPER, "--weights", weights["upper"], "--duration-s", "12", "--out", str(out),
                 "--quiet"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["target"]["name"] == "upper_stage" and summary["frames"] == 13
    det = np.load(out / "det.npz")
    assert det["corners_px"].shape == (13, 12, 2) and det["visible"].shape == (13, 12)
    # det.npz and est.npz say which target they hold, as `envisat track`'s do: the file as typed, its name, sha256
    # and keypoint names (Target.record)
    target = load_target(UPPER)
    record = {"file": UPPER, "name": "upper_stage", "sha256": target.sha256,
              "keypoint_names": list(target.keypoint_names)}
    assert json.loads(str(det["config_json"]))["target"] == record
    assert json.loads(str(np.load(out / "est.npz")["config_json"]))["target"] == record
    truth = np.load(out / "truth.npz")
    assert truth["corners_px"].shape[1:] == (12, 2)  # MuJoCo's truth of the upper stage's 12 keypoints
    # the default scenario's 50 m hold sized to the upper stage, as its generated sequences are
    ratio = size_ratio(load_target(UPPER))
    assert np.linalg.norm(truth["x"][0, :3]) == pytest.approx(50.0 * ratio, rel=1e-3)
    assert os.path.getsize(out / "recording.rrd") > 0
    assert "cold start" in capsys.readouterr().out


@pytest.mark.parametrize("argv, words", [
    (["--target", os.path.join(MODELS, "cubesat_3u.xml")], "has no keypoint detector of its own at"),  # none ships
    (["--weights", "upper"], "not ENVISAT's"),
    (["--target", UPPER, "--weights", "cubesat"], "of target 'cubesat_3u'"),
    (["--target", UPPER, "--weights", "uncalibrated"], "no calibrated pixel covariance"),
])
def test_weights_that_cannot_serve_are_refused_in_one_line(weights, tmp_path, capsys, argv, words):
    argv = [weights.get(a, a) for a in argv]
    out = tmp_path / "run"
    assert main(["run", *argv, "--duration-s", "5", "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and words in err[0], err
    assert not out.exists()


def test_the_python_tracker_of_another_target(weights):
    """tracker_from_scenario(target=...) is what `--target` builds: the target's K keypoints, its namings, the
    keypoint detector of the weights; ENVISAT's weights refused for it."""
    from envisat_pose.config import InputError
    from envisat_pose.pipelines.tracking.tracker import tracker_from_scenario

    tracker = tracker_from_scenario("default", weights["upper"], target=UPPER, size_px=(256, 256))
    assert tracker.K == 12 and tracker.namings.count == 1 and tracker.target.name == "upper_stage"
    est = tracker.step(0.0, np.zeros((256, 256), np.uint8))
    assert est.status == "acquiring" and est.measured.shape == (12,)
    with pytest.raises(InputError, match="cubesat_3u"):
        tracker_from_scenario("default", weights["cubesat"], target=UPPER)


def test_the_written_config_records_the_target_files_sha256_and_a_rerun_refuses_the_file_changed(weights, tmp_path,
                                                                                                   capsys):
    """run.config.toml records its target file's sha256 beside it ([image] target_sha256), as truth.npz does: a
    rerun from it refuses the file once it changed, in one line naming it and the recorded sha256, with nothing
    written; another --target given over the config's is taken as it is."""
    import shutil
    import tomllib

    from envisat_pose.app.cli import build_parser
    from envisat_pose.app.run import resolve_config
    from envisat_pose.target_assets import target_sha256

    target, small = tmp_path / "stage.xml", tmp_path / "small.toml"
    shutil.copy(UPPER, target)  # the same file elsewhere: the weights' target
    small.write_text("[image]\nresolution_px = 128\n")
    first, edited = tmp_path / "first", tmp_path / "edited"
    assert main(["run", "--target", str(target), "--weights", weights["upper"], "--config", str(small),
                 "--duration-s", "1", "--out", str(first), "--quiet"]) == 0
    written = first / "run.config.toml"
    recorded = tomllib.loads(written.read_text())["image"]["target_sha256"]
    assert recorded == target_sha256(str(target))
    target.write_text(target.read_text() + "<!-- edited since -->\n")
    refused(["run", "--config", str(written), "--out", str(edited), "--quiet"], capsys, edited,
            "changed since the config was written", str(target), recorded[:12])
    parse = build_parser().parse_args
    assert resolve_config(parse(["run", "--config", str(written), "--target", UPPER, "--out", "x"])
                          ).image.target == UPPER
