"""`envisat detect` writes the Detections contract plus keys and the half-turn alternative; bad weights: one line."""

import numpy as np
import pytest
import torch

from envisat_pose.app.cli import main
from envisat_pose.config import InputError
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


def test_detections_name_the_weights_and_the_data_by_sha256(tiny_dataset, tmp_path):
    """det.npz's config_json names the weights and the dataset by their sha256 beside their paths: the path alone
    (calibrate may write over its --weights) did not say which weights made the detections."""
    import hashlib
    import json
    import os

    torch.manual_seed(0)  # this test's untrained model
    w = tmp_path / "w.safetensors"
    save_weights(str(w), CornerNet(ModelConfig(input_px=64, width=16, depth=2, stem_width=8)))
    out = tmp_path / "det.npz"
    assert main(["detect", "--weights", str(w), "--data", tiny_dataset, "--out", str(out), "--quiet",
                 "--threads", "1", "--limit", "1"]) == 0
    with np.load(out, allow_pickle=False) as z:
        cfg = json.loads(str(z["config_json"]))
    assert cfg["weights_sha256"] == hashlib.sha256(w.read_bytes()).hexdigest()
    manifest = os.path.join(tiny_dataset, "manifest.json")
    assert cfg["data_manifest_sha256"] == hashlib.sha256(open(manifest, "rb").read()).hexdigest()


def test_detect_bad_weights_one_line(tiny_dataset, tmp_path, capsys):
    bad = tmp_path / "w.safetensors"
    bad.write_bytes(b"\x00" * 10)
    for path in (bad, tmp_path / "missing.safetensors"):
        assert main(["detect", "--weights", str(path), "--data", tiny_dataset, "--out",
                     str(tmp_path / "d.npz")]) == 2
        err = capsys.readouterr().err.strip()
        assert err.count("\n") == 0 and str(path) in err


def _untrained(tmp_path, extra=None):
    torch.manual_seed(0)  # this test's untrained model
    w = tmp_path / "w.safetensors"
    save_weights(str(w), CornerNet(ModelConfig(input_px=64, width=16, depth=2, stem_width=8)), extra)
    return w


def test_roi_file_replaces_the_coarse_pass(tiny_dataset, tmp_path):
    """Frames listed in --roi are cropped exactly there (crop_px is not in the contract: check via the Detector
    the verb builds, the same call), others get the coarse pass; a calibrated file's cov_scale reaches R."""
    from envisat_pose.perception.data import shard_paths
    from envisat_pose.perception.detect import load_detector
    from envisat_pose.pipelines.detector.detect import camera_samples, read_roi

    w = _untrained(tmp_path, {"cov_scale": 4.0})
    roi = tmp_path / "roi.npz"
    np.savez(roi, key=np.array(["000000001", "000000003"]), roi_px=np.array([[10, 20, 100], [0, 0, 256]]))
    rois = read_roi(str(roi))
    det = load_detector(str(w))
    assert det.cfg.cov_scale == 4.0
    for key, image, label in camera_samples(shard_paths(tiny_dataset)):
        f = det.detect(image, label["K"], roi_px=rois.get(key))
        if key in rois:
            assert np.array_equal(f.crop_px, rois[key])
    out = tmp_path / "det.npz"
    assert main(["detect", "--weights", str(w), "--data", tiny_dataset, "--out", str(out), "--quiet",
                 "--roi", str(roi), "--threads", "1"]) == 0
    with np.load(out, allow_pickle=False) as z:
        assert '"cov_scale": 4.0' in str(z["config_json"])


def test_bad_roi_file_one_line(tiny_dataset, tmp_path, capsys):
    w = _untrained(tmp_path)
    bad = tmp_path / "roi.npz"
    np.savez(bad, key=np.array(["000000001"]), roi_px=np.array([[10.0, 20.0, -5.0]]))
    for path in (bad, tmp_path / "missing.npz"):
        assert main(["detect", "--weights", str(w), "--data", tiny_dataset, "--out", str(tmp_path / "d.npz"),
                     "--roi", str(path)]) == 2
        err = capsys.readouterr().err.strip()
        assert err.count("\n") == 0 and "--roi" in err


def test_a_bad_roi_row_is_named(tmp_path):
    """A non-positive side or a NaN names the first bad row and its key; a wrong shape names the shape."""
    from envisat_pose.pipelines.detector.detect import read_roi

    path = tmp_path / "roi.npz"
    np.savez(path, key=np.array(["a", "b", "c"]), roi_px=np.array([[1.0, 2.0, 50], [3, 4, 0], [np.nan, 0, 9]]))
    with pytest.raises(InputError, match=r"row 1 \(key 'b'\) is \[3.0, 4.0, 0.0\].*side > 0 \(2 such rows\)"):
        read_roi(str(path))
    np.savez(path, key=np.array(["a", "b"]), roi_px=np.zeros((2, 2)))
    with pytest.raises(InputError, match=r"shape \(2, 2\), expected \(2, 3\)"):
        read_roi(str(path))


def test_a_damaged_roi_file_is_one_error_and_leaves_no_file_open(tmp_path):
    """A truncated .npz, an .npy and a text file given as --roi: one InputError naming the file each (a truncated
    zip was zipfile's BadZipFile, an .npy a TypeError), and no file left open (numpy's np.load keeps its own file
    open where the zip is damaged: a ResourceWarning once collected)."""
    import gc
    import warnings

    from envisat_pose.pipelines.detector.detect import read_roi

    good = tmp_path / "roi.npz"
    np.savez(good, key=np.array(["a", "b"]), roi_px=np.array([[1.0, 2.0, 50], [3, 4, 60]]))
    data = good.read_bytes()
    (tmp_path / "cut.npz").write_bytes(data[: len(data) // 2])
    np.save(tmp_path / "rows.npy", np.zeros((2, 3)))
    (tmp_path / "text.npz").write_text("a,1,2,50\n")
    for name in ("cut.npz", "rows.npy", "text.npz"):
        gc.collect()  # what earlier tests left unclosed is theirs: collected before, not counted here
        with warnings.catch_warnings(record=True) as seen:
            warnings.simplefilter("always")
            with pytest.raises(InputError, match=f"roi '.*{name}'"):
                read_roi(str(tmp_path / name))
            gc.collect()
        assert not [w for w in seen if issubclass(w.category, ResourceWarning) and name in str(w.message)], name
