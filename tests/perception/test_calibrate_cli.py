"""`envisat calibrate`: the scale fitted from held-out frames, written into the weights' metadata and read back
by load_detector; too few correctly named corners is a one-line error."""

import json

import numpy as np
import torch

from envisat_pose.app.calibrate import collect_errors
from envisat_pose.app.cli import main
from envisat_pose.app.detect import camera_samples
from envisat_pose.perception.data import shard_paths
from envisat_pose.perception.detect import FrameDetection, load_detector
from envisat_pose.perception.model import CornerNet, ModelConfig
from envisat_pose.perception.weights import read_metadata, save_weights, with_metadata


class NoisyLabelDetector:
    """Test double: the label's visible corners plus Gaussian noise of sigma 1.5 px, claiming sigma 0.5 px (a
    covariance 9x too small): the calibration must find s = 9. Half of the frames come out half-turn ambiguous
    with the right naming as the alternative (scored with the better naming)."""

    def __init__(self, seed):
        self.rng = np.random.default_rng(seed)
        self.labels = {}
        self.n = 0

    def detect(self, image, K):
        label = self.labels[self.n]
        self.n += 1
        use = label["visible"] & label["in_frame"]
        pts = np.where(use[:, None], label["corners_px"] + self.rng.normal(0, 1.5, (8, 2)), np.nan)
        cov = np.where(use[:, None, None], 0.25 * np.eye(2), np.nan)
        perm = np.array([2, 3, 0, 1, 6, 7, 4, 5])
        if self.n % 2:
            return FrameDetection(pts[perm], cov[perm], use[perm] * 1.0, use[perm], pts, 0.5, True,
                                  np.zeros(3), pts)
        return FrameDetection(pts, cov, use * 1.0, use, pts[perm], 0.0, False, np.zeros(3), pts)


def test_collect_errors_finds_the_true_scale(tiny_dataset):
    from envisat_pose.perception.calibrate import fit_scale

    det = NoisyLabelDetector(0)
    samples = list(camera_samples(shard_paths(tiny_dataset))) * 40
    det.labels = {i: s[2] for i, s in enumerate(samples)}
    err, cov, groups = collect_errors(det, samples)
    assert len(err) > 500 and len(groups) == len(err)
    assert abs(fit_scale(err, cov) - 9.0) < 0.1 * 9.0
    assert np.all(np.abs(err) < 5.0)


def test_calibrated_metadata_reaches_the_detector(tmp_path):
    torch.manual_seed(0)  # this test's untrained model
    w, out = tmp_path / "w.safetensors", tmp_path / "c.safetensors"
    save_weights(str(w), CornerNet(ModelConfig(input_px=64, width=16, depth=2, stem_width=8)))
    assert load_detector(str(w)).cfg.cov_scale == 1.0
    with_metadata(str(w), str(out), {"cov_scale": 2.25, "cov_calibration": json.dumps({"scale": 2.25})})
    assert load_detector(str(out)).cfg.cov_scale == 2.25
    assert json.loads(read_metadata(str(out))["cov_calibration"])["scale"] == 2.25


def test_too_few_corners_is_one_line(tiny_dataset, tmp_path, capsys):
    torch.manual_seed(0)  # this test's untrained model: it names nothing right
    w = tmp_path / "w.safetensors"
    save_weights(str(w), CornerNet(ModelConfig(input_px=64, width=16, depth=2, stem_width=8)))
    assert main(["calibrate", "--weights", str(w), "--data", tiny_dataset, "--out", str(tmp_path / "c.safetensors"),
                 "--quiet", "--threads", "1"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "correctly named corners" in err
    assert not (tmp_path / "c.safetensors").exists()
