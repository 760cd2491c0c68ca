"""The detection chain around the network (coarse pass, crop, decode, map back, naming) with an oracle in place
of the network (heatmaps made from the label), and the real network's output contract."""

import numpy as np
import torch

from envisat_pose.perception.data import read_samples, shard_paths, to_input_px
from envisat_pose.perception.detect import Detector
from envisat_pose.perception.heatmaps import CORNER_JTYPE, encode_junctions
from envisat_pose.perception.model import CornerNet, ModelConfig


class OracleDetector(Detector):
    """Network outputs made from the label's corners, as a perfect network would give them."""

    label = None

    def network(self, crop_u8, box):
        cells = self.input_px // self.stride
        p = to_input_px(self.label["corners_px"], box, self.input_px)
        valid = self.label["visible"] & self.label["in_frame"]
        t = encode_junctions(p, valid, CORNER_JTYPE, (cells, cells), self.stride, sigma_cells=1.0)
        jchol = np.zeros((3, cells, cells), np.float32)
        return {"jmap": t["jmap"], "joff": t["joff"], "jchol": jchol, "features": None}

    def patch_network(self, patches_u8, boxes):
        out = []
        for box in boxes:
            cells = patches_u8.shape[-1] // self.stride
            p = to_input_px(self.label["corners_px"], box, patches_u8.shape[-1])
            valid = self.label["visible"] & self.label["in_frame"]
            t = encode_junctions(p, valid, CORNER_JTYPE, (cells, cells), self.stride, sigma_cells=1.0)
            out.append({"jmap": t["jmap"], "joff": t["joff"], "jchol": np.zeros((3, cells, cells), np.float32)})
        return out

    def line_probabilities(self, features, points_in):
        return np.full((len(points_in), len(points_in)), 0.5)


def test_oracle_chain_recovers_named_corners(tiny_dataset):
    from envisat_pose.perception.detect import DetectConfig

    model = CornerNet(ModelConfig(input_px=128, width=16, depth=2, stem_width=8))
    det, crop_only = OracleDetector(model), OracleDetector(model, DetectConfig(patch_px=0))
    right = sure = 0
    n = 0
    crop_px2 = []
    for key, image, label in read_samples(shard_paths(tiny_dataset)):
        det.label = label
        f = det.detect(image, label["K"])
        want = label["visible"] & label["in_frame"]
        if want.sum() < 4:
            continue
        n += 1
        for corners in (f.corners_px, f.alt_corners_px if f.ambiguous else None):
            if corners is not None and np.all(np.abs(corners[want] - label["corners_px"][want]) < 0.05):
                right += 1
                break
        # values, not only shapes: the oracle's covariance is 1 input px^2 (a zero log-Cholesky map) and the patch
        # pass finds each corner again in a patch of patch_px / patch_zoom image px seen at patch_px input px: in
        # the frame, (1 / patch_zoom)^2 px^2; its heatmap peaks at 1 on every corner, so an unambiguous naming's
        # corners are found with confidence 1; a corner not found has none
        found = f.visible
        assert found.sum() >= 4, found
        np.testing.assert_allclose(f.cov_px[found], np.broadcast_to(np.eye(2) / det.cfg.patch_zoom**2,
                                                                    (found.sum(), 2, 2)), rtol=0, atol=1e-6)
        assert np.isnan(f.cov_px[~found]).all() and (f.confidence[~found] == 0).all()
        if not f.ambiguous:
            np.testing.assert_allclose(f.confidence[found], 1.0, atol=1e-3)
            sure += 1
        # without the patch pass: 1 input px of the crop is crop side / input_px frame px
        crop_only.label = label
        g = crop_only.detect(image, label["K"])
        px2 = (g.crop_px[2] / crop_only.input_px) ** 2
        np.testing.assert_allclose(g.cov_px[g.visible], np.broadcast_to(px2 * np.eye(2), (g.visible.sum(), 2, 2)),
                                   rtol=1e-6)
        assert g.visible.sum() >= 4
        crop_px2.append(px2)
    print(right, n)
    assert n >= 6 and right >= n - 1 and sure >= n - 1
    assert min(crop_px2) < 0.25  # crops far from the input's size: a dropped scale would show


def test_untrained_network_runs_end_to_end(tiny_dataset):
    """The real network (untrained, seeded) through every step of Detector.detect: crop, network, decode, map
    back to the frame, naming, the patch pass. With no score threshold the decode keeps top_k junctions, the
    naming matches some of them, and the frame's detection keeps its contract: named corners are candidates
    (found in the given region), their covariances symmetric positive definite, their confidences in (0, 1],
    NaN and zero confidence elsewhere."""
    from envisat_pose.perception.detect import DetectConfig

    torch.manual_seed(0)  # the test's own draw for an untrained model: not a library's
    cfg = DetectConfig(threshold=0.0, patch_threshold=0.0)
    det = Detector(CornerNet(ModelConfig(input_px=64, width=16, depth=2, stem_width=8)), cfg)
    key, image, label = next(read_samples(shard_paths(tiny_dataset)))
    roi = np.array([0, 0, 256])
    f = det.detect(image, label["K"], roi_px=roi)
    assert f.corners_px.shape == (8, 2) and f.cov_px.shape == (8, 2, 2) and f.visible.dtype == bool
    assert np.array_equal(f.crop_px, roi)
    # every junction the decode kept, mapped back inside the region (the patch pass moves one by <= its radius)
    assert f.candidates_px.shape == (cfg.top_k, 2)
    margin = cfg.patch_radius_px
    assert np.all((f.candidates_px >= -margin) & (f.candidates_px <= 256 + margin))
    # the naming matched some of them (an unmatched chain returns no visible corner at all)
    vis = f.visible
    assert vis.sum() >= 3, vis
    for c in f.corners_px[vis]:  # a named corner is one of the candidates, each used once
        assert np.sum(np.all(f.candidates_px == c, axis=1)) >= 1
    assert len(np.unique(f.corners_px[vis], axis=0)) == vis.sum()
    cov = f.cov_px[vis]
    assert np.allclose(cov, np.swapaxes(cov, 1, 2)) and np.all(np.linalg.eigvalsh(cov) > 0)
    assert np.all((f.confidence[vis] > 0) & (f.confidence[vis] <= 1))
    assert np.all(np.isnan(f.corners_px[~vis])) and np.all(np.isnan(f.cov_px[~vis])) and np.all(f.confidence[~vis] == 0)
    assert 0.0 <= f.alt_probability <= 1.0


class ShiftedOracle(OracleDetector):
    """The oracle with every junction moved 1 px along +x and its covariance claimed at 1 px^2: the sub-pixel
    refinement must pull the named corners back toward the image's corners."""

    shift = np.array([1.0, 0.0])

    def network(self, crop_u8, box):
        label = self.label
        self.label = dict(label, corners_px=label["corners_px"] + self.shift)
        out = super().network(crop_u8, box)
        self.label = label
        scale = self.input_px / float(box[2])  # 1 full-image px^2, in input px (log-Cholesky)
        out["jchol"][:2] = np.log(scale)
        return out


def test_refinement_moves_named_corners_back_to_the_image(tmp_path):
    import dataclasses

    from envisat_pose.app.cli import main

    # 6 sunlit frames of a simulated truth at 512 px (plain faces, edges long enough to fit)
    ds = tmp_path / "seq"
    assert main(["generate", "--mode", "sequence", "--num-images", "6", "--resolution", "512", "--seed", "633",
                 "--out", str(ds), "--quiet"]) == 0

    from envisat_pose.perception.detect import DetectConfig

    model = CornerNet(ModelConfig(input_px=128, width=16, depth=2, stem_width=8))
    plain = ShiftedOracle(model, DetectConfig(patch_px=0))  # the refinement alone (the patch pass would undo the shift)
    refined = ShiftedOracle(model, dataclasses.replace(plain.cfg, refine=True))
    moved, before, after = 0, [], []
    for key, image, label in read_samples(shard_paths(str(ds))):
        want = label["visible"] & label["in_frame"]
        if want.sum() < 4:
            continue
        plain.label = refined.label = label
        f0 = plain.detect(image, label["K"])
        f1 = refined.detect(image, label["K"])
        assert f1.refined is not None and f0.refined is None
        ok = f1.refined & want & f0.visible
        # the corners are the same candidates: where not refined they stay put
        same = f0.visible & ~f1.refined
        assert np.allclose(f0.corners_px[same], f1.corners_px[same])
        moved += int(ok.sum())
        before += np.abs(f0.corners_px[ok, 0] - label["corners_px"][ok, 0]).tolist()
        after += np.abs(f1.corners_px[ok, 0] - label["corners_px"][ok, 0]).tolist()
    print(moved, np.median(before), np.median(after))
    assert moved >= 8
    assert np.median(after) < 0.75 * np.median(before)  # 1 px off before; fused with the refined corner after


def test_the_folded_network_gives_the_models_detections(tiny_dataset):
    """The inference copy (batch norms folded into their convolutions, channels_last) is what runs, and it names
    the same corners as the model itself to float rounding (shipped weights, frames of the tiny dataset)."""
    from envisat_pose.perception.detect import load_detector
    from envisat_pose.perception.weights import shipped_weights_path

    det = load_detector(shipped_weights_path())
    assert det._net is not det.model
    assert not any(isinstance(m, torch.nn.BatchNorm2d) for m in det._net.modules())
    plain = load_detector(shipped_weights_path())
    plain._net = plain.model
    for _, image, label in list(read_samples(shard_paths(tiny_dataset)))[:3]:
        a, b = det.detect(image, label["K"]), plain.detect(image, label["K"])
        # a corner whose score sits within rounding of the threshold may fall either side on another CPU's kernels
        assert (a.visible != b.visible).sum() <= 1, (a.visible, b.visible)
        both = a.visible & b.visible
        assert both.sum() >= 4
        np.testing.assert_allclose(a.corners_px[both], b.corners_px[both], atol=1e-3)


def test_patch_pass_finds_the_corners_again_magnified(tiny_dataset):
    """The crop's network is 1 px off (the shifted oracle) and the magnified patches' is exact: the patch pass
    puts every named corner back on the label and gives it the patch's covariance (1 input px^2 of a patch at
    zoom 2 is 0.25 image px^2); off, the corners stay 1 px off."""
    from envisat_pose.perception.detect import DetectConfig

    model = CornerNet(ModelConfig(input_px=128, width=16, depth=2, stem_width=8))
    off = ShiftedOracle(model, DetectConfig(patch_px=0))
    on = ShiftedOracle(model, DetectConfig(patch_px=64, patch_zoom=2.0, cov_scale=1.0))
    n = 0
    for key, image, label in read_samples(shard_paths(tiny_dataset)):
        want = label["visible"] & label["in_frame"]
        if want.sum() < 4:
            continue
        off.label = on.label = label
        f0, f1 = off.detect(image, label["K"]), on.detect(image, label["K"])
        for f in (f0, f1):  # the naming may prefer the half-turn: score the naming that names the label
            if f.ambiguous and np.nanmax(np.abs(f.alt_corners_px[want] - label["corners_px"][want])) < 1.5:
                f.corners_px[:] = f.alt_corners_px
        found = want & np.isfinite(f1.corners_px[:, 0])
        assert found.sum() >= 4
        np.testing.assert_allclose(f1.corners_px[found], label["corners_px"][found], atol=0.05)
        err0 = np.abs(f0.corners_px[found, 0] - label["corners_px"][found, 0])
        assert np.all(np.abs(err0 - 1.0) < 0.05)
        np.testing.assert_allclose(f1.cov_px[found], np.broadcast_to(0.25 * np.eye(2), (found.sum(), 2, 2)), atol=1e-6)
        n += 1
    assert n >= 5
