"""Another target's keypoint network (perception/keypoint_net.py) and its weights: K channels named by the target,
the target's name, sha256 and keypoint names in the file, loaded back only for that target; ENVISAT's corner
weights keep their metadata and refuse to load as another target's."""

import dataclasses
import json
import os
import sys

import pytest
import torch

sys.path.insert(0, os.path.dirname(__file__))
from keypoint_cases import KEYPOINTS_T_M, twin_box_xml  # noqa: E402

from envisat_pose.config import ConfigError, InputError  # noqa: E402
from envisat_pose.perception.keypoint_detect import KeypointDetector, load_keypoint_model  # noqa: E402
from envisat_pose.perception.keypoint_net import KeypointModelConfig, init_keypoint_net  # noqa: E402
from envisat_pose.perception.model import CornerNet, ModelConfig  # noqa: E402
from envisat_pose.perception.weights import (  # noqa: E402
    WeightsError,
    load_backbone,
    load_model,
    read_header,
    save_weights,
    shipped_weights_path,
)
from envisat_pose.target import load_target  # noqa: E402

SMALL = KeypointModelConfig(input_px=64, width=8, depth=2, stem_width=8, num_keypoints=8)


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    folder = tmp_path_factory.mktemp("kp_weights")
    (folder / "twin.xml").write_text(twin_box_xml())
    (folder / "other.xml").write_text(twin_box_xml("twin_box"))  # same name ...
    with open(folder / "other.xml", "a") as fh:
        fh.write("<!-- another file -->\n")  # ... other bytes: another sha256
    twin = load_target(str(folder / "twin.xml"))
    record = {k: v for k, v in twin.record(twin.path).items() if k != "file"}
    weights = str(folder / "kp.safetensors")
    save_weights(weights, init_keypoint_net(SMALL, 3, record))
    return str(folder / "twin.xml"), str(folder / "other.xml"), weights


def test_the_network_has_a_channel_per_keypoint_and_its_weights_name_the_target(files):
    twin, _, weights = files
    model = init_keypoint_net(SMALL, 3)
    with torch.no_grad():
        out = model(torch.zeros((2, 1, 64, 64)))
    assert out["kmap_logit"].shape == (2, 8, 16, 16) and out["koff"].shape == (2, 8, 2, 16, 16)
    assert out["kvis_logit"].shape == (2, 8) and float(out["koff"].abs().max()) <= 0.5
    meta = read_header(weights)
    target = load_target(twin)
    assert meta["kind"] == "keypoints" and json.loads(meta["model_config"])["num_keypoints"] == 8
    assert json.loads(meta["target"]) == {"name": "twin_box", "sha256": target.sha256,
                                          "keypoint_names": list(KEYPOINTS_T_M)}
    back = load_keypoint_model(weights, twin)
    assert all(torch.equal(a, b) for a, b in zip(back.state_dict().values(),
                                                  init_keypoint_net(SMALL, 3).state_dict().values()))
    assert KeypointDetector(back).keypoint_names == tuple(KEYPOINTS_T_M)


def test_envisats_corner_weights_keep_their_metadata(tmp_path):
    path = str(tmp_path / "c.safetensors")
    save_weights(path, CornerNet(ModelConfig(input_px=64, width=8, depth=2, stem_width=8)), {"step": "1"})
    assert set(read_header(path)) == {"format", "model_config", "step"}
    load_model(path)


def test_weights_load_only_for_their_own_target(files):
    twin, other, weights = files
    with pytest.raises(InputError, match="keypoint detector of target 'twin_box'.*not ENVISAT's") as err:
        load_model(weights)
    assert "\n" not in str(err.value) and "run_detect_target" in str(err.value)  # where a Python caller goes
    import envisat_pose

    assert {"TargetDetectJobConfig", "run_detect_target", "evaluate_target_detector",
            "run_calibrate_target"} <= set(envisat_pose.__all__)
    with pytest.raises(InputError, match="ENVISAT's corner detector.*not a detector of target 'twin_box'"):
        load_keypoint_model(shipped_weights_path(), twin)
    with pytest.raises(InputError, match="not of target 'twin_box' .*other.xml, sha256.*a comment too, makes "
                       "another target"):  # the same name, a comment more: said why
        load_keypoint_model(weights, other)


def test_the_keypoint_count_comes_from_the_target(files):
    from envisat_pose.perception.keypoint_train import KeypointTrainConfig

    twin, _, _ = files
    assert KeypointTrainConfig(target=twin).model.num_keypoints == 8
    with pytest.raises(ConfigError, match="num_keypoints"):
        KeypointTrainConfig(target=twin, model=KeypointModelConfig(num_keypoints=5))
    with pytest.raises(ConfigError, match="another target than ENVISAT"):
        KeypointTrainConfig(target="models/envisat.xml")
    # replaced with another target: its count filled in again (it was refused, naming a count never given)
    narrow = KeypointTrainConfig(target=twin, model=KeypointModelConfig(width=16, stem_width=8))
    stage = dataclasses.replace(narrow, target="models/upper_stage.xml")
    built = KeypointTrainConfig(target="models/upper_stage.xml", model=KeypointModelConfig(width=16, stem_width=8))
    assert stage.model == built.model and stage.model.num_keypoints == 12
    with pytest.raises(ConfigError, match="num_keypoints"):  # a count given stays given
        dataclasses.replace(narrow, model=KeypointModelConfig(num_keypoints=8), target="models/upper_stage.xml")


def test_a_backbone_comes_from_any_detectors_weights_and_the_heads_stay_seeded(files):
    """load_backbone: the stem, hourglass and neck of ENVISAT's shipped corner network (its backbone is the
    keypoint network's default) land in a keypoint network, every head tensor as seeded; a backbone of another
    width is refused naming the tensor."""
    from envisat_pose.perception.weights import read_weights

    model = init_keypoint_net(KeypointModelConfig(num_keypoints=12), 5)
    seeded = {k: v.clone() for k, v in model.state_dict().items()}
    path = shipped_weights_path()
    copied = load_backbone(model, path)
    corner, _ = read_weights(path)
    state = model.state_dict()
    backbone = [k for k in state if k.startswith(("stem.", "hourglass.", "neck."))]
    assert copied == len(backbone) > 100
    assert all(torch.equal(state[k], corner[k]) and not torch.equal(state[k], seeded[k])
               for k in backbone if state[k].is_floating_point() and state[k].numel() > 1)
    heads = [k for k in state if k not in backbone]
    assert heads and all(torch.equal(state[k], seeded[k]) for k in heads)
    _, _, small = files
    with pytest.raises(WeightsError, match="backbone tensor 'stem.0.0.weight'.*another width"):
        load_backbone(init_keypoint_net(KeypointModelConfig(num_keypoints=8), 5), small)
