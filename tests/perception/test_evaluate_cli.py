"""`envisat evaluate` end to end: an oracle network (heatmaps made from the label of the frame it is shown) in
place of trained weights, on a small freshly generated set with the paper's corruption; and its bad inputs."""

import hashlib
import json
import pathlib

import numpy as np
import pytest

from envisat_pose.app.cli import main
from envisat_pose.config import InputError
from envisat_pose.perception.data import read_samples, shard_paths, to_input_px
from envisat_pose.perception.detect import Detector
from envisat_pose.perception.heatmaps import CORNER_JTYPE, encode_junctions
from envisat_pose.perception.model import CornerNet, ModelConfig
from envisat_pose.perception.weights import save_weights

TINY = ModelConfig(input_px=128, width=16, depth=2, stem_width=8)


class LookupOracle(Detector):
    """A perfect network: the junction targets of the label of the frame it is shown (found by its pixels)."""

    def __init__(self, model, config, labels: dict):
        super().__init__(model, config)
        self.labels = labels
        self.label = None

    def detect(self, image, K, roi_px=None, prior_R_cam_from_target=None):
        self.label = self.labels[hashlib.sha1(image.tobytes()).hexdigest()]
        return super().detect(image, K, roi_px, prior_R_cam_from_target)

    def network(self, crop_u8, box):
        cells = self.input_px // self.stride
        p = to_input_px(self.label["corners_px"], box, self.input_px)
        valid = self.label["visible"] & self.label["in_frame"]
        t = encode_junctions(p, valid, CORNER_JTYPE, (cells, cells), self.stride, sigma_cells=1.0)
        # log-Cholesky 0: a 1 input-px^2 covariance
        return {"jmap": t["jmap"], "joff": t["joff"], "jchol": np.zeros((3, cells, cells), np.float32),
                "features": None}

    def line_probabilities(self, features, points_in):
        return np.full((len(points_in), len(points_in)), 0.5)


@pytest.fixture(scope="module")
def paper_dataset(tmp_path_factory):
    """12 images of 320 px, the paper's corruption at mixed levels, written by `envisat generate`."""
    root = tmp_path_factory.mktemp("evalds")
    cfg = root / "paper.toml"
    cfg.write_text('[corruption]\nmodel = "paper"\n')
    out = root / "ds"
    assert main(["generate", "--config", str(cfg), "--num-images", "12", "--shard-size", "6", "--resolution", "320",
                 "--seed", "5", "--out", str(out), "--quiet"]) == 0
    return str(out)


@pytest.fixture(scope="module")
def weights(tmp_path_factory):
    import torch

    torch.manual_seed(0)  # the test's own draw of an untrained model
    path = tmp_path_factory.mktemp("w") / "tiny.safetensors"
    save_weights(str(path), CornerNet(TINY))
    return str(path)


def test_evaluate_with_oracle_writes_every_group(paper_dataset, weights, tmp_path, monkeypatch, capsys):
    import envisat_pose.pipelines.detector.evaluate as app

    labels = {hashlib.sha1(img.tobytes()).hexdigest(): lab for _, img, lab in read_samples(shard_paths(paper_dataset))}
    monkeypatch.setattr(app, "make_detector", lambda model, config, device: LookupOracle(model, config, labels))
    out = tmp_path / "eval.json"
    assert main(["evaluate", "--weights", weights, "--data", paper_dataset, "--json", str(out), "--quiet"]) == 0
    table = capsys.readouterr().out
    res = json.loads(out.read_text())
    from envisat_pose.perception.evaluate import GROUP_ORDER, RANGE_GROUPS

    assert list(res["groups"]) == list(GROUP_ORDER) + list(RANGE_GROUPS) and res["frames"] == 12
    assert res["weights_sha256"] == hashlib.sha256(open(weights, "rb").read()).hexdigest()  # the path alone did not
    assert sum(res["groups"][g]["detector"]["frames"] for g in RANGE_GROUPS) == 12
    allg = res["groups"]["all"]
    assert set(allg) == {"detector", "detector_no_lines", "harris", "shi_tomasi"}
    det = allg["detector"]
    # a perfect network: corners to sub-pixel where named, few swaps, honest visibility, good poses
    assert det["errors"]["all"]["median_px"] < 0.1
    assert det["pck_5px"] > 0.8 and det["swap_rate"] < 0.15  # the naming (not scored here) errs on a few
    assert det["visibility"]["precision"] > 0.9 and det["visibility"]["recall"] > 0.8
    assert det["pose"]["solved_share"] > 0.8 and det["pose"]["rotation_deg_median"] < 1.0
    assert det["pose"]["translation_m_median"] < 0.2
    assert "visibility" not in allg["harris"] and allg["harris"]["frames"] == 12
    # the partition covers every frame once; the marginals too
    part = sum(res["groups"][g]["detector"]["frames"] for g in ("clean", "noise_only", "blur_only", "combined"))
    assert part == 12
    assert sum(res["groups"][f"noise={s}"]["detector"]["frames"] for s in ("none", "low", "medium", "high")) == 12
    assert "all" in table and "shi_tomasi" in table and "PCK@5" in table
    # the verb's Python call: the same numbers from the same folder (a pathlib.Path, the config's fields)
    from envisat_pose.pipelines.detector.detect import DetectJobConfig

    again = app.run_evaluate(DetectJobConfig(weights=weights), pathlib.Path(paper_dataset), tmp_path / "again.json")
    assert again["frames"] == 12 and json.loads((tmp_path / "again.json").read_text())["groups"] == res["groups"]
    with pytest.raises(InputError, match="one region of interest at most"):
        app.run_evaluate(DetectJobConfig(weights=weights, roi=str(tmp_path / "r.npz")), paper_dataset,
                         tmp_path / "x.json", roi_labels=True)


class ScaledLabels:
    """Test double: names every usable labelled corner, moved out from the usable corners' centroid by a known
    per-frame scale (1, 1.01 or 1.02 by the frame's index); records the regions of interest it is given."""

    def __init__(self, labels: dict, scales: dict):
        self.labels, self.scales, self.rois = labels, scales, []

    def detect(self, image, K, roi_px=None, prior_R_cam_from_target=None):
        from envisat_pose.perception.detect import FrameDetection

        h = hashlib.sha1(image.tobytes()).hexdigest()
        lab, s = self.labels[h], self.scales[h]
        self.rois.append(roi_px)
        use = lab["visible"] & lab["in_frame"]
        c = lab["corners_px"][use].mean(axis=0)
        pts = np.where(use[:, None], c + s * (lab["corners_px"] - c), np.nan)
        cov = np.where(use[:, None, None], np.eye(2), np.nan)
        return FrameDetection(pts, cov, use * 1.0, use, pts, 0.0, False, np.zeros(3), pts)


def test_scale_and_radial_bias_match_the_labels(paper_dataset, weights, tmp_path, monkeypatch):
    """evaluate's apparent scale and radial error per corruption group and range bin against the same figures
    computed here from the labels (the poses and corners read from the tar members themselves)."""
    import tarfile

    import envisat_pose.pipelines.detector.evaluate as app
    from envisat_pose.perception.evaluate import RANGE_EDGES_M, RANGE_GROUPS, corruption_groups, corruption_levels

    samples = list(read_samples(shard_paths(paper_dataset)))
    labels = {hashlib.sha1(img.tobytes()).hexdigest(): lab for _, img, lab in samples}
    scales = {hashlib.sha1(img.tobytes()).hexdigest(): 1.0 + 0.01 * (i % 3) for i, (_, img, _) in enumerate(samples)}
    double = ScaledLabels(labels, scales)
    monkeypatch.setattr(app, "make_detector", lambda model, config, device: double)
    out = tmp_path / "eval.json"
    assert main(["evaluate", "--weights", weights, "--data", paper_dataset, "--json", str(out), "--quiet",
                 "--roi-labels", "--refine"]) == 0
    res = json.loads(out.read_text())
    assert sum(r is not None for r in double.rois) == 24  # detector_roi and detector_roi_refined: one per frame
    ranges = {}
    for path in shard_paths(paper_dataset):
        with tarfile.open(path) as tar:
            for m in tar.getmembers():
                if m.name.endswith(".json"):
                    ranges[m.name.split(".")[0]] = float(np.linalg.norm(json.loads(tar.extractfile(m).read())
                                                                        ["t_cam_from_target_m"]))
    per_group = {}
    for (key, img, lab) in samples:
        h = hashlib.sha1(img.tobytes()).hexdigest()
        use = lab["visible"] & lab["in_frame"]
        q = lab["corners_px"][use]
        radial = (scales[h] - 1.0) * np.linalg.norm(q - q.mean(axis=0), axis=1)
        g = corruption_groups(*corruption_levels(lab["corruption"], img.shape[1]))
        g.append(RANGE_GROUPS[int(np.searchsorted(RANGE_EDGES_M, ranges[key], side="right"))])
        for name in g:
            acc = per_group.setdefault(name, {"scale": [], "radial": []})
            if use.sum() >= 3:
                acc["scale"].append(scales[h])
            if use.sum() >= 2:
                acc["radial"] += radial.tolist()
    for name, acc in per_group.items():
        for method in ("detector", "detector_roi", "detector_refined", "detector_roi_refined"):
            b = res["groups"][name][method]["bias"]
            assert b["scale_frames"] == len(acc["scale"]) and b["radial_corners"] == len(acc["radial"])
            assert abs(b["scale_mean"] - np.mean(acc["scale"])) < 1e-9
            assert abs(b["radial_px_mean"] - np.mean(acc["radial"])) < 1e-9
            if len(acc["scale"]) > 1:
                se = np.std(acc["scale"], ddof=1) / np.sqrt(len(acc["scale"]))
                assert abs(b["scale_se"] - se) < 1e-9


def test_missing_weights_one_line(paper_dataset, tmp_path, capsys):
    rc = main(["evaluate", "--weights", str(tmp_path / "nope.safetensors"), "--data", paper_dataset, "--json",
               str(tmp_path / "e.json")])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and len(err.splitlines()) == 1 and "nope.safetensors" in err


def test_empty_dataset_one_line(weights, tmp_path, capsys):
    (tmp_path / "empty").mkdir()
    rc = main(["evaluate", "--weights", weights, "--data", str(tmp_path / "empty"), "--json", str(tmp_path / "e.json")])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and len(err.splitlines()) == 1 and "empty dataset" in err
