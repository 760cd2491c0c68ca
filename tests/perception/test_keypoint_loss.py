"""The keypoint network's loss (perception/keypoint_loss.py): on a target with a two-fold symmetry its materials
keep, a prediction equal to the twin's labels costs nothing; the same prediction costs under the identity alone, on
the target whose materials break the turn, and for a relabeling that is no symmetry. The twin's labels are the
test's own projection of the keypoints under the twin pose R R_z(180)^T (a pinhole the test writes), with the
visibility from the Target's exact ray casts, never from the permutation under test."""

import os
import sys

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

sys.path.insert(0, os.path.dirname(__file__))
from keypoint_cases import HALF_TURN_PERM, KEYPOINTS_T_M, twin_box_xml  # noqa: E402

from envisat_pose.perception.keypoint_loss import (  # noqa: E402
    KeypointLossConfig,
    encode_keypoints,
    keypoint_losses,
    relabelings,
)
from envisat_pose.perception.keypoint_net import decode_keypoints  # noqa: E402
from envisat_pose.target import load_target  # noqa: E402

S, STRIDE, F_PX = 96, 4, 120.0  # the test's input side, heatmap stride, focal length
R_Z_HALF = np.diag([-1.0, -1.0, 1.0])


@pytest.fixture(scope="module")
def targets(tmp_path_factory):
    folder = tmp_path_factory.mktemp("kp_targets")
    (folder / "twin.xml").write_text(twin_box_xml())
    (folder / "painted.xml").write_text(twin_box_xml("painted_box", painted=True))
    return load_target(str(folder / "twin.xml")), load_target(str(folder / "painted.xml"))


def project(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """The keypoints through the test's pinhole (principal point at the input's centre), (K, 2) px."""
    X = np.array(list(KEYPOINTS_T_M.values())) @ R.T + t
    return F_PX * X[:, :2] / X[:, 2:] + (S - 1) / 2


def labels(target, R: np.ndarray, t: np.ndarray) -> dict:
    """The encoded labels of the pose (R_K_from_T, t), visibility from the target's ray casts."""
    px = torch.from_numpy(project(R, t))[None]
    visible = torch.from_numpy(target.visible(R, t))[None]
    return encode_keypoints(px, visible, (S // STRIDE, S // STRIDE), STRIDE, 1.0)


def prediction_of(lab: dict) -> dict:
    """The network output that says exactly these labels: heatmap logits +-30 at the cells, the offsets there, the
    visibility logits +-30."""
    n, k, h, w = lab["kmap"].shape
    koff = torch.zeros((n, k, 2, h * w))
    for j in range(k):
        koff[0, j, :, lab["kcell"][0, j]] = lab["koff"][0, j]
    return {"kmap_logit": torch.where(lab["kmap"] >= 1, 30.0, -30.0), "koff": koff.reshape(n, k, 2, h, w),
            "kvis_logit": torch.where(lab["valid"], 30.0, -30.0)}


POSES = [(Rotation.from_euler("xyz", a, degrees=True).as_matrix(), np.array([0.1, -0.05, 5.0]))
         for a in ((20, -30, 10), (-120, 15, 70), (60, 40, -150))]


def test_the_materials_decide_which_half_turns_relabel(targets):
    twin, painted = targets
    X = np.array(list(KEYPOINTS_T_M.values()))
    np.testing.assert_allclose(X @ R_Z_HALF.T, X[HALF_TURN_PERM], atol=1e-12)  # the test's own twin map
    assert relabelings(twin.symmetries, 8).tolist() == [list(range(8)), HALF_TURN_PERM]
    assert relabelings(painted.symmetries, 8).tolist() == [list(range(8))]


@pytest.mark.parametrize("pose", range(len(POSES)))
def test_a_prediction_equal_to_the_twins_labels_costs_nothing(targets, pose):
    twin, painted = targets
    R, t = POSES[pose]
    truth = labels(twin, R, t)
    twin_labels = labels(twin, R @ R_Z_HALF.T, t)  # the pose whose image is the same
    assert not torch.equal(twin_labels["kcell"], truth["kcell"])  # the twin's names sit elsewhere
    guess = prediction_of(twin_labels)
    cfg = KeypointLossConfig()
    perms = torch.as_tensor(relabelings(twin.symmetries, 8))
    both = keypoint_losses(guess, truth, perms, cfg)
    assert float(both["loss"]) < 1e-6 and float(both["twin"]) == 1.0
    assert all(float(both[term]) < 1e-6 for term in ("heatmap", "offset", "visibility"))  # the chosen labeling's
    assert float(keypoint_losses(prediction_of(truth), truth, perms, cfg)["loss"]) < 1e-6
    alone = keypoint_losses(guess, truth, perms[:1], cfg)
    assert float(alone["loss"]) > 1.0 and float(alone["twin"]) == 0.0
    broken = torch.as_tensor(relabelings(painted.symmetries, 8))  # the painted fin tells the twins apart
    assert torch.equal(broken, perms[:1])
    swap = torch.tensor([[1, 0, 2, 3, 4, 5, 6, 7]])  # a relabeling that is no symmetry
    assert float(keypoint_losses(guess, truth, torch.cat([perms[:1], swap]), cfg)["loss"]) > 1.0


def test_each_sample_takes_its_own_smallest_labeling(targets):
    """A batch of a twin's guess and a truthful guess: each sample's loss is its own minimum (0 for both), the
    batch's twin share one half."""
    twin, _ = targets
    R, t = POSES[0]
    a, b = labels(twin, R, t), labels(twin, R @ R_Z_HALF.T, t)
    batch = {k: torch.cat([a[k], a[k]]) for k in a}
    pa, pb = prediction_of(a), prediction_of(b)
    guess = {k: torch.cat([pa[k], pb[k]]) for k in pa}
    out = keypoint_losses(guess, batch, torch.as_tensor(relabelings(twin.symmetries, 8)), KeypointLossConfig())
    assert float(out["loss"]) < 1e-6 and float(out["twin"]) == 0.5


def test_the_peak_and_its_offset_decode_to_the_subpixel_keypoint(targets):
    twin, _ = targets
    R, t = POSES[1]
    lab = labels(twin, R, t)
    pred = prediction_of(lab)
    d = decode_keypoints(torch.sigmoid(pred["kmap_logit"][0]).numpy(), pred["koff"][0].numpy(), STRIDE)
    ok = lab["valid"][0].numpy()
    np.testing.assert_allclose(d["points_px"][ok], project(R, t)[ok], atol=1e-4)
