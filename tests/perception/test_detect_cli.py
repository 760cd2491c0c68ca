"""`envisat detect` writes the Detections contract plus keys and the half-turn alternative; bad weights: one line."""

import numpy as np
import torch

from envisat_pose.app.cli import main
from envisat_pose.contracts import Detections
from envisat_pose.perception.model import CornerNet, ModelConfig
from envisat_pose.perception.weights import save_weights


def test_detect_writes_detections(tiny_dataset, tmp_path):
    torch.manual_seed(0)  # this test's untrained model
    w = tmp_path / "w.safetensors"
    save_weights(str(w), CornerNet(ModelConfig(input_px=64, width=16, depth=2, stem_width=8)))
    out = tmp_path / "det.npz"
    assert main(["detect", "--weights", str(w), "--data", tiny_dataset, "--out", str(out), "--quiet",
                 "--threads", "1"]) == 0
    det = Detections.load(str(out))
    assert det.corners_px.shape == (8, 8, 2) and det.cov_px.shape == (8, 8, 2, 2)
    with np.load(out, allow_pickle=False) as z:
        assert list(z["key"]) == [f"{i:09d}" for i in range(8)]
        assert z["alt_corners_px"].shape == (8, 8, 2) and z["ambiguous"].dtype == bool


def test_detect_bad_weights_one_line(tiny_dataset, tmp_path, capsys):
    bad = tmp_path / "w.safetensors"
    bad.write_bytes(b"\x00" * 10)
    for path in (bad, tmp_path / "missing.safetensors"):
        assert main(["detect", "--weights", str(path), "--data", tiny_dataset, "--out",
                     str(tmp_path / "d.npz")]) == 2
        err = capsys.readouterr().err.strip()
        assert err.count("\n") == 0 and str(path) in err
