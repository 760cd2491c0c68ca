"""Another target's default weights (job_defaults.default_target_weights): its own keypoint detector,
FILE_detector.safetensors beside its MJCF file, taken where no weights are given, by every verb and Python call
that takes a target and weights: the shipped upper stage is detected with its shipped detector, and the records
name it as 'models/...' (no path of this machine); a file beside a target holding another target's weights is
refused in one line, nothing written; where none is beside it the refusal names where it was looked for as the
user typed the target."""

import json
import os
import shutil
import sys

import numpy as np
import pytest

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))  # the folder's own helpers
sys.path.insert(0, os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "perception"))
from keypoint_cases import twin_box_xml, untrained_weights  # noqa: E402
from refusals import refused  # noqa: E402

from envisat_pose.app.cli import main  # noqa: E402
from envisat_pose.config import InputError  # noqa: E402
from envisat_pose.pipelines.common.job_defaults import job_record, models_folder  # noqa: E402

os.environ.setdefault("MUJOCO_GL", "osmesa")
# the repository's models folder, by this file's place: the tests run from any working folder
MODELS = os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))), "models")
UPPER = os.path.join(MODELS, "upper_stage.xml")
SHIPPED_UPPER = "models/upper_stage_detector.safetensors"  # as records name the package's file


@pytest.fixture(scope="module")
def upper_frames(tmp_path_factory):
    """Two labelled 128 px frames of the shipped upper stage (seed 3)."""
    data = tmp_path_factory.mktemp("upper") / "data"
    assert main(["generate", "--target", UPPER, "--num-images", "2", "--resolution", "128", "--seed", "3",
                 "--out", str(data), "--quiet"]) == 0
    return str(data)


@pytest.fixture
def foreign_beside(tmp_path):
    """A test-built target twin.xml with twin_detector.safetensors beside it: the untrained weights of another
    target (twin_copy, the same shape under another name). Returns the folder."""
    (tmp_path / "twin.xml").write_text(twin_box_xml())
    (tmp_path / "copy.xml").write_text(twin_box_xml("twin_copy"))
    untrained_weights(tmp_path / "twin_detector.safetensors", tmp_path / "copy.xml", sigma_px=1.5)
    (tmp_path / "data").mkdir()
    return tmp_path


def test_the_shipped_upper_stage_is_detected_with_its_own_shipped_weights(upper_frames, tmp_path, capsys):
    out = tmp_path / "det.npz"
    assert main(["detect", "--target", UPPER, "--data", upper_frames, "--out", str(out), "--quiet"]) == 0
    det = np.load(out)
    assert det["keypoints_px"].shape == (2, 12, 2)
    record = json.loads(str(det["config_json"]))
    assert record["weights"] == SHIPPED_UPPER and record["target"]["name"] == "upper_stage"
    assert "2 frames of target upper_stage" in capsys.readouterr().out


def test_the_python_calls_behind_the_verbs_take_the_targets_own_weights():
    """TargetDetectJobConfig (detect, evaluate, calibrate --target), RunConfig, TrackConfig and
    tracker_from_scenario, given the upper stage and no weights: its shipped detector, recorded as 'models/...'."""
    from envisat_pose.pipelines.detector.detect_target import TargetDetectJobConfig
    from envisat_pose.pipelines.jobs import resolve_job
    from envisat_pose.pipelines.tracking.tracker import tracker_from_scenario

    shipped = os.path.join(models_folder(), "upper_stage_detector.safetensors")
    assert os.path.samefile(TargetDetectJobConfig(target=UPPER).weights, shipped)
    run = resolve_job("run", "default", None, {"image.target": UPPER})
    track = resolve_job("track", "default", None, target=UPPER)
    for cfg in (run, track):
        assert os.path.samefile(cfg.weights, shipped) and job_record(cfg)["weights"] == SHIPPED_UPPER
    tracker = tracker_from_scenario("default", target=UPPER, size_px=(128, 128))
    assert tracker.K == 12 and tracker.detector.trained_for["name"] == "upper_stage"


@pytest.mark.parametrize("verb", [["detect", "--out", "OUT"], ["evaluate", "--json", "OUT"],
                                  ["calibrate", "--out", "OUT"], ["run", "--out", "OUT"]])
def test_another_targets_weights_beside_a_target_are_refused_in_one_line(foreign_beside, capsys, verb):
    out = str(foreign_beside / "out")
    data = [] if verb[0] == "run" else ["--data", str(foreign_beside / "data")]
    argv = [verb[0], *[out if a == "OUT" else a for a in verb[1:]], "--target", str(foreign_beside / "twin.xml")]
    refused(argv + data + ["--quiet"], capsys, out, "--weights ''", "twin_detector.safetensors", "'twin_copy'",
            "not of target 'twin_box'")


def test_the_python_calls_refuse_another_targets_weights_beside_the_target(foreign_beside):
    from envisat_pose.pipelines.detector.detect_target import TargetDetectJobConfig
    from envisat_pose.pipelines.tracking.tracker import tracker_from_scenario

    twin = str(foreign_beside / "twin.xml")
    for build in (lambda: TargetDetectJobConfig(target=twin), lambda: tracker_from_scenario("default", target=twin)):
        with pytest.raises(InputError, match="twin_detector.safetensors.*'twin_copy'"):
            build()


def test_no_default_is_named_as_the_user_typed_the_target(foreign_beside, monkeypatch, capsys):
    """detect --target twin.xml (relative) with nothing beside it: the line names 'twin_detector.safetensors', no
    path of this machine (it named the shipped ENVISAT weights by their absolute path)."""
    os.remove(foreign_beside / "twin_detector.safetensors")
    monkeypatch.chdir(foreign_beside)
    err = refused(["detect", "--target", "twin.xml", "--data", "data", "--out", "det.npz", "--quiet"], capsys,
                  "det.npz", "--weights '': none given", "no keypoint detector of its own at "
                  "'twin_detector.safetensors'", "or save it as 'twin_detector.safetensors'")
    assert str(foreign_beside) not in err and os.path.realpath(models_folder()) not in err, err


def test_a_users_own_weights_beside_their_target_are_its_default(foreign_beside, tmp_path, monkeypatch):
    """The weights `envisat train --target` wrote for a user's file, saved beside it: taken, and recorded as the
    user would type them (relative to the working folder as the target was)."""
    from envisat_pose.pipelines.detector.detect_target import TargetDetectJobConfig

    untrained_weights(foreign_beside / "twin_detector.safetensors", foreign_beside / "twin.xml", sigma_px=1.5)
    shutil.copy(foreign_beside / "twin.xml", foreign_beside / "data" / "twin.xml")  # not beside: no weights
    monkeypatch.chdir(foreign_beside)
    assert TargetDetectJobConfig(target="twin.xml").weights == "twin_detector.safetensors"
    with pytest.raises(InputError, match="no keypoint detector of its own at 'data/twin_detector.safetensors'"):
        TargetDetectJobConfig(target="data/twin.xml")


def test_a_target_file_that_is_not_there_is_named_before_its_default_weights(tmp_path, capsys):
    """No --weights and a --target that names no file: one line naming --target (the default's search looked in
    a folder that is not there and stopped with a traceback)."""
    missing = str(tmp_path / "nowhere" / "sat.xml")
    for verb, flag in (("detect", "--out"), ("evaluate", "--json")):
        refused([verb, "--target", missing, "--data", str(tmp_path), flag, str(tmp_path / "out" / "x")], capsys,
                str(tmp_path / "out"), "--target", "sat.xml", "no such file")


@pytest.mark.parametrize("argv", [["detect", "--data", "DATA", "--out", "OUT/det.npz"], ["run", "--out", "OUT"]])
def test_envisats_shipped_weights_given_for_another_target_are_named_as_typed(upper_frames, tmp_path, capsys, argv):
    """`--weights models/detector.safetensors` for the upper stage: refused in one line naming them as typed (it
    named the package's file by this machine's path)."""
    out = str(tmp_path / "out")
    argv = [a.replace("DATA", upper_frames).replace("OUT", out) for a in argv]
    err = refused(argv[:1] + ["--target", UPPER, "--weights", "models/detector.safetensors"] + argv[1:], capsys, out,
                  "--weights 'models/detector.safetensors'", "ENVISAT's corner detector")
    assert os.path.join(os.path.realpath(models_folder()), "detector.safetensors") not in err, err
