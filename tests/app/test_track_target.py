"""`envisat track --target FILE.xml` (another spacecraft's frames, its keypoint detector): a short sequence of the
shipped upper stage tracked end to end by an untrained, calibrated keypoint network (the plumbing, not the
tracking: the outputs carry the target's K = 12 keypoints and its record); the refusals (ENVISAT's weights, no
weights, uncalibrated weights for the upper stage; its dataset tracked as ENVISAT's or as another target's, and
ENVISAT's as the upper stage's) are one line each, with nothing written."""

import json
import os
import re
import shutil
import sys

import numpy as np
import pytest

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))  # the folder's own helpers
sys.path.insert(0, os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "perception"))
from keypoint_cases import untrained_weights  # noqa: E402
from refusals import refused  # noqa: E402

from envisat_pose.app.cli import main
from envisat_pose.target import load_target

os.environ.setdefault("MUJOCO_GL", "osmesa")
UPPER_STAGE = os.path.join(os.path.dirname(load_target().path), "upper_stage.xml")
FRAMES = 25


@pytest.fixture(scope="module")
def stage(tmp_path_factory):
    """(a 25-frame sequence of the upper stage at 96 px, its calibrated and uncalibrated untrained weights, a copy
    of its file under another model name with calibrated weights of its own, a 2-frame ENVISAT sequence)."""
    folder = tmp_path_factory.mktemp("track_target")
    seq = str(folder / "seq")
    assert main(["generate", "--target", UPPER_STAGE, "--mode", "sequence", "--num-images", str(FRAMES),
                 "--resolution", "96", "--seed", "3", "--workers", "1", "--out", seq, "--quiet"]) == 0
    other = folder / "other_stage.xml"  # the same shape, another file (sha256) and name
    text = open(UPPER_STAGE).read()
    other.write_text(text.replace('<mujoco model="upper_stage">', '<mujoco model="other_stage">', 1))
    envisat = str(folder / "envisat")
    assert main(["generate", "--mode", "sequence", "--num-images", "2", "--resolution", "64", "--workers", "1",
                 "--out", envisat, "--quiet"]) == 0
    return {"seq": seq, "calibrated": untrained_weights(str(folder / "cal.safetensors"), UPPER_STAGE, 1.5),
            "uncalibrated": untrained_weights(str(folder / "raw.safetensors"), UPPER_STAGE, None),
            "other": str(other), "other_weights": untrained_weights(str(folder / "other.safetensors"), str(other), 1.5),
            "envisat": envisat}


def test_an_upper_stage_sequence_is_tracked_with_its_keypoint_detector(stage, tmp_path, capsys):
    from envisat_pose.contracts import Estimates
    from envisat_pose.datagen.dataset import iter_samples

    out = tmp_path / "run"
    assert main(["track", "--images", stage["seq"], "--target", UPPER_STAGE, "--weights", stage["calibrated"],
                 "--out", str(out), "--quiet"]) == 0
    assert f"{FRAMES} frames of 96 x 96 px" in capsys.readouterr().out
    assert {"est.npz", "det.npz", "track.config.toml", "summary.json", "recording.rrd", "errors.png"} <= \
        set(os.listdir(out))
    target = load_target(UPPER_STAGE)
    keys = [key for key, _, _ in iter_samples(stage["seq"])]
    with np.load(out / "det.npz", allow_pickle=False) as det:
        assert det["corners_px"].shape == (FRAMES, 12, 2) and det["visible"].shape == (FRAMES, 12)
        assert det["key"].tolist() == keys  # every frame, in time order, named by its sample
        assert json.loads(str(det["config_json"]))["target"]["sha256"] == target.sha256
    summary = json.loads((out / "summary.json").read_text())
    assert summary["source"]["frames"] == FRAMES and summary["source"]["kind"] == "dataset"
    assert sum(summary["frames_by_status"].values()) == FRAMES and "scores" in summary
    assert summary["target"]["name"] == "upper_stage" and summary["target"]["sha256"] == target.sha256
    assert summary["target"]["keypoint_names"] == list(target.keypoint_names)
    est = Estimates.load(str(out / "est.npz"))
    assert est.x_hat.shape == (1, FRAMES, 12) and est.x_true.shape == (1, FRAMES, 12)
    truth = np.array([label["x"] for _, label, _ in iter_samples(stage["seq"])])
    assert np.allclose(est.x_true[0], truth)  # the labels' truth, scored
    assert json.loads(est.config_json)["track"]["target"] == UPPER_STAGE
    assert re.search(r'^target = ".*upper_stage\.xml"$', (out / "track.config.toml").read_text(), re.M)




def test_the_upper_stage_without_its_calibrated_weights_is_refused(stage, tmp_path, capsys):
    from envisat_pose.pipelines.common.job_defaults import default_weights_path

    out = str(tmp_path / "out")
    alone = tmp_path / "upper_stage.xml"  # the shipped file elsewhere: no detector beside it
    shutil.copy(UPPER_STAGE, alone)
    track = ["track", "--images", stage["seq"], "--target", str(alone), "--out", out, "--quiet"]
    refused(track, capsys, out, "--weights ''", "no keypoint detector of its own", "envisat train --target",
            "envisat calibrate --target")
    shipped = default_weights_path()
    refused(track + ["--weights", shipped], capsys, out, "--weights 'models/detector.safetensors'",  # as recorded
            "ENVISAT's corner detector", "target 'upper_stage'")
    refused(track + ["--weights", stage["uncalibrated"]], capsys, out, "--weights", stage["uncalibrated"],
            "no calibrated pixel covariance", "envisat calibrate --target")
    refused(["track", "--images", stage["seq"], "--target", str(tmp_path / "none.xml"), "--out", out], capsys, out,
            "--target '", "none.xml", "no such file")  # a config error of a flag typed names the flag


def test_a_dataset_of_another_target_than_the_jobs_is_refused(stage, tmp_path, capsys):
    out = str(tmp_path / "out")
    refused(["track", "--images", stage["seq"], "--out", out, "--quiet"], capsys, out, "--images", stage["seq"],
            "target 'upper_stage'", "not of ENVISAT", "--target")
    refused(["track", "--images", stage["seq"], "--target", stage["other"], "--weights", stage["other_weights"],
             "--out", out, "--quiet"], capsys, out, "--images", "target 'upper_stage'", "not of target 'other_stage'")
    refused(["track", "--images", stage["envisat"], "--target", UPPER_STAGE, "--weights", stage["calibrated"],
             "--out", out, "--quiet"], capsys, out, "--images", "target 'envisat'", "not of target 'upper_stage'")
    # `envisat adapt` knows ENVISAT only: the upper stage's frames are refused as before
    refused(["adapt", "--images", stage["seq"], "--out", out, "--quiet"], capsys, out, "--images",
            "target 'upper_stage'", "not of ENVISAT")


def test_the_written_config_records_the_target_files_sha256_and_a_rerun_refuses_the_file_changed(stage, tmp_path,
                                                                                                   capsys):
    """track.config.toml records its target file's sha256 beside it (target_sha256), as summary.json does: a
    rerun from it refuses the file once it changed, in one line naming it and the recorded sha256, with nothing
    written; another --target given over the config's is taken as it is."""
    import shutil
    import tomllib

    from envisat_pose.pipelines.jobs import resolve_job
    from envisat_pose.target_assets import target_sha256

    target = tmp_path / "stage.xml"
    shutil.copy(UPPER_STAGE, target)  # the same file elsewhere: the frames' and the weights' target
    first, edited = tmp_path / "first", str(tmp_path / "edited")
    assert main(["track", "--images", stage["seq"], "--target", str(target), "--weights", stage["calibrated"],
                 "--out", str(first), "--quiet"]) == 0
    written = first / "track.config.toml"
    recorded = tomllib.loads(written.read_text())["target_sha256"]
    assert recorded == target_sha256(str(target))
    target.write_text(target.read_text() + "<!-- edited since -->\n")
    refused(["track", "--images", stage["seq"], "--config", str(written), "--out", edited], capsys, edited,
            "changed since the config was written", str(target), recorded[:12])
    assert resolve_job("track", "default", str(written), target=UPPER_STAGE).target == UPPER_STAGE
