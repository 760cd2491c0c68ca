"""`envisat calibrate`: the scale fitted from held-out frames, written into the weights' metadata and read back
by load_detector; too few correctly named corners is a one-line error."""

import hashlib
import json

import numpy as np
import torch

from envisat_pose.app.cli import main
from envisat_pose.perception.data import shard_paths
from envisat_pose.perception.detect import FrameDetection, load_detector
from envisat_pose.perception.model import CornerNet, ModelConfig
from envisat_pose.perception.weights import read_metadata, save_weights, with_metadata
from envisat_pose.pipelines.detector.calibrate import collect_errors
from envisat_pose.pipelines.detector.detect import camera_samples


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
    from envisat_pose.perception.calibrate import fit_cov_scale

    det = NoisyLabelDetector(0)
    samples = list(camera_samples(shard_paths(tiny_dataset))) * 40
    det.labels = {i: s[2] for i, s in enumerate(samples)}
    err, cov, groups = collect_errors(det, samples)
    assert len(err) > 500 and len(groups) == len(err)
    assert abs(fit_cov_scale(err, cov) - 9.0) < 0.1 * 9.0
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
    out = tmp_path / "new" / "deep" / "c.safetensors"
    assert main(["calibrate", "--weights", str(w), "--data", tiny_dataset, "--out", str(out), "--quiet",
                 "--threads", "1"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "correctly named corners" in err
    assert not (tmp_path / "new").exists()  # refused: no output, nor its folders


class ScaledLabelDetector:
    """Test double for a sequence: the label's usable corners scaled by 1 % about their centroid (an outward bias),
    claiming a 1 px^2 covariance; it must be given the labels' region of interest."""

    def __init__(self, labels):
        self.labels = labels
        self.n = 0
        self.rois = []

    def detect(self, image, K, roi_px=None, prior_R_cam_from_target=None):
        label = self.labels[self.n]
        self.n += 1
        self.rois.append(roi_px)
        use = label["visible"] & label["in_frame"]
        c = label["corners_px"][use].mean(axis=0)
        pts = np.where(use[:, None], c + 1.01 * (label["corners_px"] - c), np.nan)
        cov = np.where(use[:, None, None], np.eye(2), np.nan)
        return FrameDetection(pts, cov, use * 1.0, use, pts, 0.0, False, np.zeros(3), pts)


def test_sequence_error_model_written_and_loaded(tmp_path, monkeypatch, capsys):
    import envisat_pose.perception.detect as pd

    seq = tmp_path / "seq"
    assert main(["generate", "--mode", "sequence", "--num-images", "12", "--shard-size", "6", "--resolution", "256",
                 "--seed", "13", "--out", str(seq), "--quiet"]) == 0
    samples = list(camera_samples(shard_paths(str(seq))))
    double = ScaledLabelDetector([s[2] for s in samples])
    torch.manual_seed(0)  # this test's untrained model (its tensors are copied, never run)
    w, out = tmp_path / "w.safetensors", tmp_path / "c.safetensors"
    save_weights(str(w), CornerNet(ModelConfig(input_px=64, width=16, depth=2, stem_width=8)))
    with_metadata(str(w), str(w), {"cov_scale": 1.5})
    monkeypatch.setattr(pd, "load_detector", lambda *a, **k: double)
    assert main(["calibrate", "--weights", str(w), "--data", str(seq), "--out", str(out), "--roi", "labels",
                 "--keep-scale", "--quiet", "--threads", "1"]) == 0
    assert all(r is not None and r[2] >= 64 for r in double.rois)
    monkeypatch.undo()
    meta = read_metadata(str(out))
    assert meta["cov_scale"] == "1.5"  # kept
    model = load_detector(str(out)).error_model
    assert model.n_frames == 12 and "roi=labels" in model.source
    # the data named by its folder and its manifest's sha256, never by a path of this machine
    manifest = hashlib.sha256((seq / "manifest.json").read_bytes()).hexdigest()
    assert f"seq (manifest sha256 {manifest[:16]})" in model.source
    assert not any(str(tmp_path) in v for v in meta.values())
    usable = [s[2]["visible"] & s[2]["in_frame"] for s in samples]
    framed = sum(int(u.sum() >= 3) for u in usable)
    record = json.loads(meta["error_model_record"])
    assert record["scale"]["frames"] == framed
    assert abs(model.bias_scale - 1.01) < 1e-9 and model.bias_radial_px > 0
    errs = np.concatenate([(0.01 * (s[2]["corners_px"] - s[2]["corners_px"][u].mean(axis=0)))[u]
                           for s, u in zip(samples, usable)])
    assert abs(model.cov_scale - np.mean(np.sum(errs ** 2, axis=1)) / 2) < 1e-9
    assert "rho_lag1" in capsys.readouterr().out


def stale_weights(path) -> None:
    """Untrained weights as calibrated earlier: a scale with an error model measured on sequences beside it, a
    refinement floor and a face cue (the last two other fits')."""
    torch.manual_seed(0)  # this test's untrained model (its tensors are copied, never run)
    save_weights(str(path), CornerNet(ModelConfig(input_px=64, width=16, depth=2, stem_width=8)))
    model = json.dumps({"cov_scale": 1.5, "inflation": 4.0, "n_frames": 120, "rho_lag1": 0.4,
                        "source": "roi=coarse; seq (manifest sha256 feedfacefeedface)"})
    with_metadata(str(path), str(path), {"cov_scale": 1.5, "cov_calibration": json.dumps({"scale": 1.5}),
                                         "error_model": model, "error_model_record": json.dumps({"n": 120}),
                                         "refine_cov_floor_px2": 0.08, "face_cue": "{}"})


def test_a_new_scale_on_random_views_removes_the_earlier_error_model(tiny_dataset, tmp_path, monkeypatch, capsys):
    """A new cov_scale fitted on random views replaces the earlier calibration whole: its error model (measured
    on sequences at the old scale) is removed and the verb says so; the other fits' keys stay. --keep-scale keeps
    the scale and the error model that belongs to it."""
    import envisat_pose.perception.detect as pd

    w = tmp_path / "w.safetensors"
    stale_weights(w)
    samples = list(camera_samples(shard_paths(tiny_dataset))) * 5
    for keep, out in ((False, tmp_path / "new.safetensors"), (True, tmp_path / "kept.safetensors")):
        det = NoisyLabelDetector(0)
        det.labels = {i: s[2] for i, s in enumerate(samples)}
        monkeypatch.setattr(pd, "load_detector", lambda *a, **k: det)
        assert main(["calibrate", "--weights", str(w), "--data", *[tiny_dataset] * 5, "--out", str(out), "--quiet",
                     "--threads", "1", *(["--keep-scale"] if keep else [])]) == 0
        monkeypatch.undo()
        meta, said = read_metadata(str(out)), capsys.readouterr().out
        assert meta["refine_cov_floor_px2"] == "0.08" and meta["face_cue"] == "{}"
        if keep:
            assert meta["cov_scale"] == "1.5" and "error_model" in meta and "error_model_record" in meta
            assert "removed" not in said
            continue
        assert abs(float(meta["cov_scale"]) - 9.0) < 0.3 * 9.0
        assert "error_model" not in meta and "error_model_record" not in meta
        assert pd.weights_error_model(str(out)).n_frames == 0  # the white default
        assert ("error model from the earlier calibration removed: measured on sequences of roi=coarse; seq "
                "(manifest sha256 feedfacefeedface) (120 frames)") in said


class RefinedLabelDetector:
    """Test double for --refine: the label's usable corners; the even-numbered ones 'refined' with errors of
    sigma 0.3 px claiming sigma 0.1 px (a floor of 0.09 - 0.01 = 0.08 px^2 makes them honest), the others with
    errors of sigma 2 px (ignored)."""

    def __init__(self, labels, seed):
        self.labels, self.n, self.rng = labels, 0, np.random.default_rng(seed)

    def detect(self, image, K, roi_px=None, prior_R_cam_from_target=None):
        label = self.labels[self.n % len(self.labels)]
        self.n += 1
        use = label["visible"] & label["in_frame"]
        refined = use & (np.arange(8) % 2 == 0)
        sigma = np.where(refined, 0.3, 2.0)[:, None]
        pts = np.where(use[:, None], label["corners_px"] + sigma * self.rng.standard_normal((8, 2)), np.nan)
        cov = np.where(use[:, None, None], np.where(refined[:, None, None], 0.01, 4.0) * np.eye(2), np.nan)
        return FrameDetection(pts, cov, use * 1.0, use, pts, 0.0, False, np.zeros(3), pts, refined=refined)


def test_refine_floor_fitted_on_the_refined_corners(tiny_dataset, tmp_path, monkeypatch):
    import envisat_pose.perception.detect as pd

    samples = list(camera_samples(shard_paths(tiny_dataset)))
    double = RefinedLabelDetector([s[2] for s in samples], 1)
    torch.manual_seed(0)  # this test's untrained model (its tensors are copied, never run)
    w, out = tmp_path / "w.safetensors", tmp_path / "r.safetensors"
    save_weights(str(w), CornerNet(ModelConfig(input_px=64, width=16, depth=2, stem_width=8)))
    with_metadata(str(w), str(w), {"cov_scale": 1.5})
    monkeypatch.setattr(pd, "load_detector", lambda *a, **k: double)
    data = [tiny_dataset] * 30  # the same 8 frames, new noise each time
    assert main(["calibrate", "--weights", str(w), "--data", *data, "--out", str(out), "--refine", "--quiet",
                 "--threads", "1"]) == 0
    monkeypatch.undo()
    meta = read_metadata(str(out))
    assert meta["cov_scale"] == "1.5" and "error_model" not in meta
    floor = float(meta["refine_cov_floor_px2"])
    assert abs(floor - 0.08) < 0.015
    det = load_detector(str(out))
    assert det.cfg.refine_cov_floor_px2 == floor and det.cfg.cov_scale == 1.5


class RenamingDetector(NoisyLabelDetector):
    """The label's corners with a covariance of its own for each (corner k: diag(k + 1, 2 k + 1) / 10 px^2); every
    frame half-turn ambiguous, its first naming the half-turn's (each corner with its candidate's covariance) and
    the right one the alternative."""

    def detect(self, image, K):
        label = self.labels[self.n]
        self.n += 1
        use = label["visible"] & label["in_frame"]
        pts = np.where(use[:, None], label["corners_px"], np.nan)
        cov = np.where(use[:, None, None], own_covariances(), np.nan)
        perm = np.array([2, 3, 0, 1, 6, 7, 4, 5])
        return FrameDetection(pts[perm], cov[perm], use[perm] * 1.0, use[perm], pts, 0.5, True, np.zeros(3), pts)


def own_covariances() -> np.ndarray:
    return np.stack([np.diag([(k + 1) / 10, (2 * k + 1) / 10]) for k in range(8)])


def test_a_frame_scored_under_its_alternative_naming_takes_its_corners_covariances_along(tiny_dataset):
    """The frames are scored under the right naming (the alternative): each corner's covariance must be that
    corner's own, as the candidate carries it, not the covariance of the corner its first naming gave that name."""
    from envisat_pose.pipelines.detector.calibrate import collect_frames

    det = RenamingDetector(0)
    samples = list(camera_samples(shard_paths(tiny_dataset)))
    det.labels = {i: s[2] for i, s in enumerate(samples)}
    rows = collect_frames(det, samples)
    hit = np.isfinite(rows["err_px"][..., 0])
    assert hit.sum() > 20
    want = np.broadcast_to(own_covariances(), rows["cov_px"].shape)
    assert np.array_equal(rows["cov_px"][hit], want[hit])
