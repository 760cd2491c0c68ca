"""`envisat train --target FILE.xml` and `envisat detect --target FILE.xml` on a target the tests write (issue 56,
item 1 and part of 2): a short training run writes weights recording the target, `detect --target` loads them and
writes the KeypointDetections contract; the same weights are refused for ENVISAT and for another target file, and
ENVISAT's weights for another target, by every verb that loads weights: exit 2, one line naming the weights, their
target and the given one, nothing written."""

import json
import os
import sys

import numpy as np
import pytest

sys.path.insert(0, os.path.join(os.path.dirname(os.path.dirname(__file__)), "perception"))
from keypoint_cases import KEYPOINTS_T_M, SMALL_TRAIN, twin_box_xml, untrained_weights  # noqa: E402

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))  # the folder's own helpers
from refusals import refused  # noqa: E402

from envisat_pose.app.cli import main  # noqa: E402
from envisat_pose.contracts import KeypointDetections  # noqa: E402
from envisat_pose.io import sha256_file  # noqa: E402
from envisat_pose.target import load_target  # noqa: E402

os.environ.setdefault("MUJOCO_GL", "osmesa")


@pytest.fixture(scope="module")
def box(tmp_path_factory):
    """(the target file, another file of the same shape, a 2-frame dataset of the target at 96 px, untrained
    keypoint weights recording the target, a 2-frame ENVISAT sequence at 64 px)."""
    folder = tmp_path_factory.mktemp("train_target")
    path, other = folder / "twin.xml", folder / "other.xml"
    path.write_text(twin_box_xml())
    other.write_text(twin_box_xml("twin_copy"))
    data = folder / "data"
    assert main(["generate", "--target", str(path), "--num-images", "2", "--resolution", "96", "--seed", "4",
                 "--out", str(data), "--quiet"]) == 0
    weights = untrained_weights(folder / "untrained.safetensors", path)
    envisat = folder / "envisat"
    assert main(["generate", "--mode", "sequence", "--num-images", "2", "--resolution", "64", "--out", str(envisat),
                 "--quiet"]) == 0
    return str(path), str(other), str(data), weights, str(envisat)




def test_weights_are_refused_for_another_target_by_every_verb(box, tmp_path, capsys):
    path, other, data, weights, envisat = box
    out = str(tmp_path / "out")
    refused(["detect", "--target", "models/upper_stage.xml", "--weights", "models/detector.safetensors", "--data",
             data, "--out", f"{out}/det.npz"], capsys, out, "detector.safetensors", "ENVISAT's corner detector",
            "target 'upper_stage'")  # given: without --weights the upper stage's own are its default
    for argv in (["detect", "--data", data, "--out", f"{out}/det.npz"],
                 ["calibrate", "--data", data, "--out", f"{out}/w.safetensors"],
                 ["evaluate", "--data", data, "--json", f"{out}/e.json"],
                 ["run", "--duration-s", "5", "--out", out],
                 ["track", "--images", envisat, "--out", out],
                 ["adapt", "--images", envisat, "--out", out]):
        refused(argv[:1] + ["--weights", weights] + argv[1:], capsys, out, "--weights", weights,
                "keypoint detector of target 'twin_box'", "not ENVISAT's")
    refused(["detect", "--target", other, "--weights", weights, "--data", data, "--out", f"{out}/det.npz"],
            capsys, out, weights, "target 'twin_box'", "not of target 'twin_copy'", "other.xml")
    refused(["train", "--online", "--init", weights, "--steps", "1", "--out", out], capsys, out, "--init",
            "target 'twin_box'", "not ENVISAT's")
    refused(["train", "--target", other, "--init", weights, "--steps", "1", "--out", out], capsys, out, "--init",
            "not of target 'twin_copy'")
    refused(["train", "--target", path, "--backbone", weights, "--init", weights, "--steps", "1", "--out", out],
            capsys, out, "backbone and init")
    refused(["train", "--target", path, "--backbone", f"{out}.safetensors", "--steps", "1", "--out", out], capsys,
            out, "--backbone", "no such weights file")
    small = tmp_path / "small.toml"  # a 16-channel network: the untrained weights' 8-channel backbone does not fit
    small.write_text(SMALL_TRAIN)
    refused(["train", "--target", path, "--config", str(small), "--backbone", weights, "--steps", "1", "--out", out,
             "--resolution", "96", "--render-workers", "1", "--quiet"], capsys, out, weights, "backbone tensor",
            "another width")
    refused(["detect", "--target", path, "--data", str(tmp_path), "--weights", weights, "--roi", "r.npz",
             "--out", f"{out}/det.npz"], capsys, out, "--roi", "not with --target")
    refused(["train", "--target", path, "--data", data, "--out", out], capsys, out, "--data", "not both")


def test_detect_target_writes_the_keypoint_contract(box, tmp_path, capsys):
    """The plumbing with untrained weights: every frame, the target's K keypoints by name, scores and
    probabilities in [0, 1]; a dataset of another target is refused."""
    path, other, data, weights, envisat = box
    out = tmp_path / "det.npz"
    assert main(["detect", "--target", path, "--weights", weights, "--data", data, "--out", str(out),
                 "--quiet"]) == 0
    det = KeypointDetections.load(str(out))
    assert det.keypoints_px.shape == (2, 8, 2) and det.keypoint_names.tolist() == list(KEYPOINTS_T_M)
    assert det.key.tolist() == sorted(det.key.tolist()) and np.all(det.crop_px[:, 2] > 0)
    assert json.loads(det.config_json)["target"]["sha256"] == load_target(path).sha256
    refused(["detect", "--target", path, "--weights", weights, "--data", envisat, "--out",
             str(tmp_path / "x" / "det.npz")], capsys, str(tmp_path / "x"), "a dataset of target 'envisat'")


@pytest.mark.slow  # two short online runs (a renderer process each) and a detection: 12 s quiet, 55 s loaded (2 cores)
def test_a_short_run_trains_resumes_and_its_weights_detect(box, tmp_path, capsys):
    """`envisat train --target` (online renders of the test's target at 128 px, a 64 px network) for 24 steps,
    resumed to 30: the weights record the target and load in `detect --target`; the run's record names the
    target. (Accuracy is not asked of so short a run: 200 such steps took the loss from ~5.0 to ~3.1.)"""
    path, _, data, _, _ = box
    cfg = tmp_path / "small.toml"
    cfg.write_text(SMALL_TRAIN)
    run = str(tmp_path / "run")
    common = ["--out", run, "--render-workers", "1", "--quiet"]
    assert main(["train", "--target", path, "--config", str(cfg), "--resolution", "128", "--uses-per-frame", "4",
                 "--steps", "24", *common]) == 0
    assert main(["train", "--resume", "--steps", "30", *common]) == 0
    state = json.load(open(os.path.join(run, "state.json")))
    assert state["step"] == 30 and state["online"]["step"] == 30
    record = json.load(open(os.path.join(run, "config.json")))
    target = load_target(path)
    assert record["target"] == {"name": "twin_box", "sha256": target.sha256, "keypoint_names": list(KEYPOINTS_T_M)}
    assert record["train"]["target"] == path and record["resumes"][0]["step"] == 24
    lines = [json.loads(x) for x in open(os.path.join(run, "metrics.jsonl"))]
    assert [line["step"] for line in lines] == [24, 30] and all(np.isfinite(line["loss"]) for line in lines)
    assert all(0 <= line["twin"] <= 1 for line in lines)  # the share of samples its twin's labeling won
    weights = os.path.join(run, "checkpoint.safetensors")
    out = tmp_path / "det.npz"
    assert main(["detect", "--target", path, "--weights", weights, "--data", data, "--out", str(out),
                 "--quiet"]) == 0
    det = KeypointDetections.load(str(out))
    assert det.keypoints_px.shape == (2, 8, 2) and np.all((det.visible_prob >= 0) & (det.visible_prob <= 1))
    run2 = str(tmp_path / "from_backbone")  # a new run whose backbone is the first run's: recorded by name and hash
    assert main(["train", "--target", path, "--config", str(cfg), "--resolution", "128", "--steps", "2",
                 "--backbone", weights, "--out", run2, "--render-workers", "1", "--quiet"]) == 0
    assert json.load(open(os.path.join(run2, "config.json")))["backbone"] == {
        "name": "checkpoint.safetensors", "sha256": sha256_file(weights)}


def test_a_new_target_run_starts_from_the_shipped_backbone_where_it_fits(box):
    """train_detector's backbone (and `envisat train --backbone`): by default a new run of another target whose
    model has the shipped network's width, depth and stem starts from ENVISAT's backbone; a narrower model, a
    run given init or resumed, and ENVISAT's own runs start as they are; 'none' is from scratch, a file is kept."""
    from envisat_pose.perception.keypoint_net import KeypointModelConfig
    from envisat_pose.perception.keypoint_train import KeypointTrainConfig
    from envisat_pose.perception.train import TrainConfig
    from envisat_pose.perception.weights import shipped_weights_path
    from envisat_pose.pipelines.detector.train import resolve_backbone

    path = box[0]
    wide = KeypointTrainConfig(target=path)
    narrow = KeypointTrainConfig(target=path, model=KeypointModelConfig(width=16, stem_width=8))
    assert resolve_backbone(None, wide, True) == shipped_weights_path()
    assert resolve_backbone(None, narrow, True) is None  # another shape: from scratch, not an error
    assert resolve_backbone(None, wide, False) is None  # init given or resumed: the run's own network
    assert resolve_backbone(None, TrainConfig(), False) is None
    assert resolve_backbone("none", wide, True) is None
    assert resolve_backbone("shipped", narrow, True) == shipped_weights_path()  # asked for: its shape checked later
    assert resolve_backbone(box[3], wide, True) == box[3]


def test_the_target_calls_take_a_folder_as_a_str_or_a_path(box, tmp_path):
    """The Python calls of detect, evaluate and calibrate --target take paths as a str or a pathlib.Path, one folder
    for a list of one, as every verb's call does: run_detect_target given a Path detected every frame, then stopped
    on writing its record (TypeError); run_calibrate_target read a str folder as its characters ("data 'd': no
    such folder") and a Path not at all (TypeError)."""
    from pathlib import Path

    from envisat_pose import TargetDetectJobConfig, evaluate_target_detector, run_calibrate_target, run_detect_target
    from envisat_pose.config import InputError

    path, other, data, weights, envisat = box
    cfg = TargetDetectJobConfig(target=path, weights=weights)
    run_detect_target(cfg, Path(data), tmp_path / "det.npz")
    assert json.loads(KeypointDetections.load(str(tmp_path / "det.npz")).config_json)["data"] == data
    assert evaluate_target_detector(cfg, Path(data), tmp_path / "e.json")["frames"] == 2
    for folder in (data, Path(data), [Path(data)]):  # 2 frames of 8 keypoints: never the 20 correct a fit needs
        with pytest.raises(InputError, match="correct detections of any keypoint in 2 frames") as err:
            run_calibrate_target(cfg, folder, tmp_path / "w.safetensors")
        assert str(err.value).startswith(f"data {str(data)!r}: at most")  # the folder as given, not its card's name
    assert sorted(os.listdir(tmp_path)) == ["det.npz", "e.json"]


def test_train_detector_renders_a_target_online_by_default_as_the_verb(box, tmp_path, monkeypatch):
    """`envisat train --target FILE` implies --online (the target's views at 512 px); train_detector given the same
    KeypointTrainConfig and no online source refused it ("trains on frames of it rendered ..., not on shards").
    The training itself is stood in for: what it is handed is the point."""
    from envisat_pose.perception.keypoint_train import KeypointTrainConfig
    from envisat_pose.pipelines.detector import train as pipeline

    path = box[0]
    handed = {}
    monkeypatch.setattr(pipeline, "_train_locked", lambda *args: handed.update(online=args[12]) or {})
    pipeline.train_detector(KeypointTrainConfig(target=path, steps=1), [], tmp_path / "run", backbone="none")
    online = handed["online"]
    assert isinstance(online, pipeline.TargetOnlineConfig) and len(online.looks) == 1
    look = online.looks[0].generate
    assert look.target == path and look.mode == "random" and look.resolution_px == pipeline.TARGET_RESOLUTION_PX
