"""Full frames in, named corners out (no label used): coarse pass, crop, network, decode, line verification, naming.

Plain numpy at the boundary: `Detector.detect(image_u8, K)` returns a FrameDetection of arrays in full-image
pixels (OpenCV convention), the per-frame slice of the core's Detections contract plus the half-turn alternative.

Steps: (1) coarse: the whole frame, padded to a square and resized to the input, gives junctions whose extent
sets the crop (skipped when the caller gives a region of interest, e.g. the filter's prediction); (2) the crop
is resized to the input and run again; (3) the top junctions are decoded with their type probabilities and
2x2 covariances (input px^2, scaled to full px^2); (4) every pair is scored by line verification; (5)
perception/naming.py fits the box and names them.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
import torch

from envisat_pose.geometry import EDGES, load_geometry
from envisat_pose.perception.box_symmetry import face_windings
from envisat_pose.perception.data import IMAGE_MEAN, IMAGE_STD, DataConfig, crop_box, crop_resize, to_full_px
from envisat_pose.perception.errormodel import ErrorModel
from envisat_pose.perception.facecue import FaceCue, half_turn_llr, weigh_naming
from envisat_pose.perception.heatmaps import decode_junctions
from envisat_pose.perception.model import CornerNet
from envisat_pose.perception.naming import Naming, name_corners
from envisat_pose.perception.naming_config import NamingConfig
from envisat_pose.perception.refine import RefineConfig, refine_named
from envisat_pose.perception.weights import WeightsError, load_model, read_metadata
from envisat_pose.perception.weights_keys import COV_SCALE_KEY, ERROR_MODEL_KEY, FACE_CUE_KEY, REFINE_FLOOR_KEY


@dataclass(frozen=True)
class DetectConfig:
    """top_k: junctions kept per crop; threshold: least junction score; coarse_threshold: the same in the coarse
    pass; crop_margin: crop side over the coarse junctions' extent; line_verification: False names the corners
    without the line head's edge scores (the evaluation's ablation); face_cue: weigh the half-turn namings by the
    swapped faces' appearance where the weights carry a fitted cue (perception/facecue.py; False: ablation);
    roi_input_px: the network's input side for a given region of interest (0: the model's input_px; the crop
    only has to find and name the corners when the patch pass places them); patch_px: find each named corner
    again in a patch of the full frame magnified patch_zoom times, resized to patch_px input px (0: off;
    Detector._patch_pass), the junction nearest the first find within patch_radius_px scoring at least
    patch_threshold (measured on 150 held-out views: median error 1.04 -> 0.57 px, mean radial error +0.17 ->
    +0.04 px; in the closed loop RMSE 3.6 -> 0.4 cm, the level of ideal pixel measurements);
    cov_scale: the calibration factor s applied to the network's covariances, C -> s C (perception/calibrate.py;
    shipped in the weights' metadata); refine:
    move each named corner to the intersection of its edges fitted to the full-resolution pixels
    (perception/refine.py), with that fit's covariance + refine_cov_floor_px2 x I in place of the network's (its
    own calibration, fitted by `envisat calibrate --refine` and shipped as `refine_cov_floor_px2`);
    refine_config: its settings; bf16: run the network in bfloat16 (torch.autocast; its maps handed on in float32),
    native on CPUs with AVX512-BF16 or AMX (bench/detector_bf16.py: accuracy beside float32 on held-out frames),
    emulated and slower elsewhere."""

    top_k: int = 12
    threshold: float = 0.2
    coarse_threshold: float = 0.2
    crop_margin: float = 1.4
    line_verification: bool = True
    cov_scale: float = 1.0
    naming: NamingConfig = NamingConfig()
    face_cue: bool = True
    roi_input_px: int = 192
    patch_px: int = 96
    patch_zoom: float = 1.5
    patch_radius_px: float = 3.0
    patch_threshold: float = 0.01
    refine: bool = False
    refine_cov_floor_px2: float = 0.0
    refine_config: RefineConfig = RefineConfig()
    bf16: bool = False


@dataclass(frozen=True)
class FrameDetection:
    """One frame. corners_px (8, 2), cov_px (8, 2, 2) px^2, confidence (8,), visible (8,) bool (found and
    named; positions NaN elsewhere); alt_corners_px (8, 2) the half-turn naming, alt_probability its
    probability, ambiguous; crop_px (3,) (x0, y0, side); candidates_px (K, 2) the unnamed junctions;
    refined (8,) bool the corners moved by the sub-pixel refinement (None: it was not asked for)."""

    corners_px: np.ndarray
    cov_px: np.ndarray
    confidence: np.ndarray
    visible: np.ndarray
    alt_corners_px: np.ndarray
    alt_probability: float
    ambiguous: bool
    crop_px: np.ndarray
    candidates_px: np.ndarray
    refined: np.ndarray | None = None

    @staticmethod
    def missing(crop: np.ndarray, K: int = 8) -> "FrameDetection":
        """Nothing found in the crop (x0, y0, side) px: K keypoints (ENVISAT's 8 corners by default), none visible."""
        nan = np.full((K, 2), np.nan)
        return FrameDetection(nan, np.full((K, 2, 2), np.nan), np.zeros(K), np.zeros(K, bool), nan.copy(), 0.0,
                              False, np.asarray(crop, np.float64), np.zeros((0, 2)))


def weights_cov_scale(path: str, key: str = COV_SCALE_KEY) -> float:
    """The covariance calibration factor stored in a weights file's metadata (`cov_scale`; 1.0 when the weights
    were never calibrated). WeightsError when it is there but not a positive number."""
    import json

    raw = read_metadata(path).get(key, "1.0")
    try:
        scale = float(json.loads(raw))
    except (ValueError, TypeError):
        scale = float("nan")
    if not np.isfinite(scale) or scale <= 0:
        raise WeightsError(f"{path}: metadata {key} {raw!r} is not a positive number")
    return scale


def weights_refine_floor(path: str) -> float:
    """The refinement's covariance floor stored in a weights file's metadata (`refine_cov_floor_px2`, px^2; 0.0
    when absent). WeightsError when it is there but not a non-negative number."""
    import json

    raw = read_metadata(path).get(REFINE_FLOOR_KEY, "0.0")
    try:
        floor = float(json.loads(raw))
    except (ValueError, TypeError):
        floor = float("nan")
    if not np.isfinite(floor) or floor < 0:
        raise WeightsError(f"{path}: metadata {REFINE_FLOOR_KEY} {raw!r} is not a non-negative number")
    return floor


def weights_error_model(path: str) -> ErrorModel:
    """The error model stored in a weights file's metadata (`error_model`, perception/errormodel.py; its
    defaults, inflation 1 and rho 0, when the file has none). WeightsError when it is there but unreadable."""

    raw = read_metadata(path).get(ERROR_MODEL_KEY)
    try:
        model = ErrorModel.from_json(raw)
    except (ValueError, TypeError) as err:
        raise WeightsError(f"{path}: metadata {ERROR_MODEL_KEY} is not readable ({err})") from None
    if not (np.isfinite(model.inflation) and model.inflation > 0 and abs(model.rho_lag1) < 1):
        raise WeightsError(f"{path}: metadata error_model has rho_lag1 {model.rho_lag1}, inflation "
                           f"{model.inflation}: expected |rho| < 1 and a positive inflation")
    if not (np.isfinite(model.bias_scale) and model.bias_scale > 0 and np.isfinite(model.bias_scale_sd)
            and model.bias_scale_sd >= 0):
        raise WeightsError(f"{path}: metadata error_model has bias_scale {model.bias_scale}, bias_scale_sd "
                           f"{model.bias_scale_sd}: expected a positive scale and a non-negative spread")
    return model


def cell_covariances(jchol: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """The 2x2 covariances (K, 2, 2), input px^2, of the heatmap cells (rows, cols) from the network's
    log-Cholesky map jchol (3, H, W): L = [[exp a, 0], [c, exp b]], C = L L^T."""
    a, b, c = (jchol[n, rows, cols] for n in range(3))
    l11, l22 = np.exp(a), np.exp(b)
    return np.stack([np.stack([l11 * l11, l11 * c], -1), np.stack([l11 * c, c * c + l22 * l22], -1)], -2)


def weights_face_cue(path: str) -> FaceCue | None:
    """The half-turn's appearance cue stored in a weights file's metadata (`face_cue`, perception/facecue.py;
    None when the file has none). WeightsError when it is there but unreadable."""

    try:
        return FaceCue.from_json(read_metadata(path).get(FACE_CUE_KEY))
    except (ValueError, TypeError, KeyError) as err:
        raise WeightsError(f"{path}: metadata {FACE_CUE_KEY} is not readable ({err})") from None


def load_detector(path: str, config: DetectConfig | None = None, device: str = "cpu", bf16: bool = False
                  ) -> "Detector":
    """A Detector from a weights file (perception/weights.py), with the covariance calibration stored in the
    file's metadata (`cov_scale`, `refine_cov_floor_px2`) unless `config` is given (its own then stand), the error model
    (`error_model`, on `detector.error_model`); bf16: DetectConfig.bf16 on that config."""

    model = load_model(path, device=device)
    cfg = config or dataclasses.replace(DetectConfig(), cov_scale=weights_cov_scale(path),
                                        refine_cov_floor_px2=weights_refine_floor(path))
    cfg = dataclasses.replace(cfg, bf16=cfg.bf16 or bf16)
    return Detector(model, cfg, device=device, error_model=weights_error_model(path), face_cue=weights_face_cue(path))


def fold_batch_norms(module: torch.nn.Module) -> None:
    """In place: every Conv2d that a BatchNorm2d follows in the same module's registration order is folded with
    it (eval statistics) and the norm replaced by an identity. Only right where the forward applies them in that
    order: inference_network checks the outputs."""
    from torch.nn.utils.fusion import fuse_conv_bn_eval

    names = list(module._modules)
    for i, name in enumerate(names):
        child = module._modules[name]
        nxt = module._modules[names[i + 1]] if i + 1 < len(names) else None
        if isinstance(child, torch.nn.Conv2d) and isinstance(nxt, torch.nn.BatchNorm2d):
            module._modules[name] = fuse_conv_bn_eval(child, nxt)
            module._modules[names[i + 1]] = torch.nn.Identity()
        elif child is not None:
            fold_batch_norms(child)


def inference_network(model: CornerNet, tol: float = 1e-4) -> CornerNet:
    """A copy of the eval-mode model for inference: batch norms folded into their convolutions and the weights
    in channels_last (on one CPU core 31.3 -> 26.4 ms per 320 px input, measured). Checked at once against the
    model on a seeded random input (every output and the line head); the model itself where any differs by more
    than tol (float rounding is ~3e-6)."""
    import copy

    net = copy.deepcopy(model)
    fold_batch_norms(net)
    net = net.to(memory_format=torch.channels_last).eval()
    p = next(model.parameters())
    g = torch.Generator().manual_seed(0)
    x = torch.randn((1, 1, model.cfg.input_px, model.cfg.input_px), generator=g).to(p.device)
    segs = (torch.rand((1, 3, 2, 2), generator=g) * model.cfg.input_px).to(p.device)
    with torch.inference_mode():
        a, b = model(x), net(x.contiguous(memory_format=torch.channels_last))
        same = all(torch.allclose(a[k], b[k], atol=tol, rtol=0) for k in a)
        same = same and torch.allclose(model.line_logits(a["features"], segs), net.line_logits(b["features"], segs),
                                       atol=tol, rtol=0)
    return net if same else model


class Detector:
    """A trained CornerNet (eval mode) and the detection steps around it."""

    def __init__(self, model: CornerNet, config: DetectConfig = DetectConfig(), device: str = "cpu",
                 error_model: ErrorModel = ErrorModel(), face_cue: FaceCue | None = None):
        self.model = model.to(device).eval()
        self._net = inference_network(self.model)  # what runs: folded and channels_last (or the model itself)
        self.cfg = config
        # what a filter needs of the errors: correlation, inflation, bias (perception/errormodel.py)
        self.error_model = error_model
        # the half-turn's appearance cue (perception/facecue.py; None: the corners and junction types alone)
        self.face_cue = face_cue if config.face_cue else None
        self._geometry = load_geometry()
        self._windings = face_windings(self._geometry)
        self.device = torch.device(device)
        self.input_px = model.cfg.input_px
        self.stride = model.cfg.stride

    def _forward(self, x: torch.Tensor) -> dict[str, torch.Tensor]:
        """The network on a batch (B, 1, S, S), in bfloat16 where cfg.bf16 says, its outputs in float32."""
        with torch.inference_mode(), torch.autocast(self.device.type, dtype=torch.bfloat16, enabled=self.cfg.bf16):
            out = self._net(x.to(self.device).contiguous(memory_format=torch.channels_last))
        return {k: v.float() for k, v in out.items()} if self.cfg.bf16 else out

    def network(self, crop_u8: np.ndarray, box: np.ndarray) -> dict[str, np.ndarray | torch.Tensor]:
        """Run the network on one input-sized uint8 crop (of the frame's box (x0, y0, side)): jmap (J, H, W) scores, joff (2, H, W), jchol (3, H, W)
        as numpy, and the features (a tensor kept for line verification)."""
        x = (crop_u8.astype(np.float32) / 255.0 - IMAGE_MEAN) / IMAGE_STD
        out = self._forward(torch.from_numpy(x)[None, None])
        return {"jmap": torch.sigmoid(out["jmap_logit"][0]).cpu().numpy(), "joff": out["joff"][0].cpu().numpy(),
                "jchol": out["jchol"][0].cpu().numpy(), "features": out["features"]}

    def line_probabilities(self, features, points_in: np.ndarray) -> np.ndarray:
        """(K, K) symmetric probability that a box edge joins junctions i and j (input px positions (K, 2))."""
        k = len(points_in)
        i, j = np.triu_indices(k, 1)
        prob = np.zeros((k, k))
        if len(i):
            segs = torch.from_numpy(np.stack([points_in[i], points_in[j]], axis=1)[None].astype(np.float32))
            with torch.inference_mode():
                logits = self._net.line_logits(features, segs.to(self.device))[0].cpu().numpy()
            prob[i, j] = prob[j, i] = 1.0 / (1.0 + np.exp(-logits))
        return prob

    def coarse_box(self, image: np.ndarray) -> np.ndarray | None:
        """The crop (x0, y0, side) around the junctions of the whole frame, or None when there are none."""
        h, w = image.shape
        whole = np.array([0, 0, max(h, w)])
        out = self.network(crop_resize(image, whole, self.input_px), whole)
        d = decode_junctions(out["jmap"], out["joff"], self.stride, top_k=self.cfg.top_k,
                             threshold=self.cfg.coarse_threshold)
        if len(d["points_px"]) == 0:
            return None
        pts = to_full_px(d["points_px"], whole, self.input_px)
        return crop_box(pts, np.ones(len(pts), bool), (h, w), DataConfig(crop_margin=self.cfg.crop_margin), None)

    def detect(self, image: np.ndarray, K: np.ndarray, roi_px: np.ndarray | None = None,
               prior_R_cam_from_target: np.ndarray | None = None,
               prior_t_cam_from_target_m: np.ndarray | None = None,
               prior_weighs_namings: bool = True) -> FrameDetection:
        """Named corners of one full frame (H, W) uint8 with intrinsics K (3, 3). roi_px: (x0, y0, side) crop to
        use instead of the coarse pass; prior_R_cam_from_target: a predicted attitude for the half-turn (R_K_from_T,
        T to the camera frame K); prior_t_cam_from_target_m: with it, the predicted pose the naming starts from
        (T's origin in K, m; naming.name_corners); prior_weighs_namings: False where the prior only seeds the
        naming's fit and the half-turn's probability is to come from the image alone."""
        if image.ndim != 2 or image.dtype != np.uint8:
            raise ValueError(f"expected an 8-bit grayscale frame, got {image.dtype} of shape {image.shape}")
        h, w = image.shape
        box = np.asarray(roi_px, dtype=np.int64) if roi_px is not None else self.coarse_box(image)
        if box is None:
            return FrameDetection.missing(np.zeros(3))
        n_in = self.cfg.roi_input_px if roi_px is not None and self.cfg.roi_input_px else self.input_px
        out = self.network(crop_resize(image, box, n_in), box)
        d = decode_junctions(out["jmap"], out["joff"], self.stride, top_k=self.cfg.top_k,
                             threshold=self.cfg.threshold)
        if len(d["points_px"]) < 4:
            return FrameDetection.missing(box)
        scale = float(box[2]) / n_in
        pts = to_full_px(d["points_px"], box, n_in)
        rows, cols = d["cell"][:, 0], d["cell"][:, 1]
        jm = out["jmap"][:, rows, cols].T  # (K, J)
        type_prob = jm / np.maximum(jm.sum(axis=1, keepdims=True), 1e-9)
        cov = cell_covariances(out["jchol"], rows, cols) * (scale ** 2 * self.cfg.cov_scale)
        edge = self.line_probabilities(out["features"], d["points_px"]) if self.cfg.line_verification else None
        naming = name_corners(pts, K, score=d["score"], type_prob=type_prob, edge_prob=edge, image_size=(w, h),
                              prior_R_cam_from_target=prior_R_cam_from_target, config=self.cfg.naming,
                              geometry=self._geometry, prior_t_cam_from_target_m=prior_t_cam_from_target_m,
                              prior_weighs_namings=prior_weighs_namings)
        if naming is None:
            return FrameDetection.missing(box)
        if self.face_cue is not None:  # the half-turn settled by what the swapped faces look like
            llr = half_turn_llr(self.face_cue, image, naming.R_cam_from_target, naming.t_cam_from_target_m, K,
                                self._geometry, self._windings)
            naming = weigh_naming(naming, llr, self.cfg.naming.ambiguity)
        if self.cfg.patch_px:
            pts, cov = self._patch_pass(image, naming, pts, cov)
        refined = None
        if self.cfg.refine:
            pts, cov, refined = self._refine(image, naming, pts, cov)
        f = self._frame(naming, pts, d["score"], cov, box)
        return f if refined is None else dataclasses.replace(f, refined=refined & f.visible)

    def _patch_pass(self, image: np.ndarray, naming: Naming, pts: np.ndarray, cov: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray]:
        """The candidates the naming matched, found again by the network in a patch of the full frame around
        each (side patch_px / patch_zoom px, resized to patch_px: patch_zoom input px per image px, one batch):
        the junction nearest the candidate within patch_radius_px replaces it, with its covariance. The crop's
        scale (input px per image px, ~0.6 at 50 m) blurs what the network sees of a corner; the patch shows it
        magnified. A candidate keeps its index, so the half-turn naming sees it moved too."""
        found = np.flatnonzero(naming.visible & naming.matched)
        idx = naming.candidate[found]
        if len(idx) == 0:
            return pts, cov
        n_in = self.cfg.patch_px
        side = max(int(round(n_in / self.cfg.patch_zoom)), 8)
        boxes = [np.array([*np.round(pts[c] - side / 2.0).astype(int), side], dtype=np.int64) for c in idx]
        outs = self.patch_network(np.stack([crop_resize(image, b, n_in) for b in boxes]), boxes)
        pts, cov = pts.copy(), cov.copy()
        scale = side / float(n_in)
        for c, box, out in zip(idx, boxes, outs):
            d = decode_junctions(out["jmap"], out["joff"], self.stride, top_k=self.cfg.top_k,
                                 threshold=self.cfg.patch_threshold)
            if len(d["points_px"]) == 0:
                continue
            cand = to_full_px(d["points_px"], box, n_in)
            j = int(np.argmin(np.linalg.norm(cand - pts[c], axis=1)))
            if np.linalg.norm(cand[j] - pts[c]) > self.cfg.patch_radius_px:
                continue
            pts[c] = cand[j]
            cov[c] = cell_covariances(out["jchol"], d["cell"][j:j + 1, 0], d["cell"][j:j + 1, 1])[0] * (
                scale ** 2 * self.cfg.cov_scale)
        return pts, cov

    def patch_network(self, patches_u8: np.ndarray, boxes: list[np.ndarray]) -> list[dict[str, np.ndarray]]:
        """The network on a batch of uint8 patches (N, P, P) (of the frame's boxes (x0, y0, side)), one
        forward: per patch jmap (J, h, w) scores, joff (2, h, w), jchol (3, h, w) as numpy."""
        x = (patches_u8.astype(np.float32) / 255.0 - IMAGE_MEAN) / IMAGE_STD
        out = self._forward(torch.from_numpy(x)[:, None])
        jmap = torch.sigmoid(out["jmap_logit"]).cpu().numpy()
        joff, jchol = out["joff"].cpu().numpy(), out["jchol"].cpu().numpy()
        return [{"jmap": jmap[n], "joff": joff[n], "jchol": jchol[n]} for n in range(len(x))]

    def _refine(self, image: np.ndarray, naming: Naming, pts: np.ndarray, cov: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The candidates the naming matched, refined (perception/refine.py): new (pts (K, 2), cov (K, 2, 2)),
        refined (8,) bool per corner. A candidate keeps its index, so the half-turn naming sees it moved too;
        the refinement's covariance plus refine_cov_floor_px2 on both axes replaces the network's, or, with
        refine_config.fuse, the two estimates are combined by their information."""

        found = naming.visible & naming.matched
        named = np.where(found[:, None], pts[np.maximum(naming.candidate, 0)], np.nan)
        new, new_cov, done = refine_named(image, named, naming.projected_px, naming.visible, EDGES,
                                          self.cfg.refine_config)
        pts, cov = pts.copy(), cov.copy()
        for k in np.flatnonzero(done & found):
            c = naming.candidate[k]
            cov_r = new_cov[k] + self.cfg.refine_cov_floor_px2 * np.eye(2)
            if self.cfg.refine_config.fuse and np.all(np.isfinite(cov[c])):
                # the network's estimate and the refined one weighed by their information (taken as independent)
                info_n, info_r = np.linalg.inv(cov[c]), np.linalg.inv(cov_r)
                cov[c] = np.linalg.inv(info_n + info_r)
                pts[c] = cov[c] @ (info_n @ pts[c] + info_r @ new[k])
            else:
                pts[c], cov[c] = new[k], cov_r
        return pts, cov, done & found

    @staticmethod
    def _frame(naming: Naming, pts: np.ndarray, score: np.ndarray, cov: np.ndarray, box: np.ndarray
               ) -> FrameDetection:
        found = naming.visible & naming.matched
        idx = np.maximum(naming.candidate, 0)
        corners = np.where(found[:, None], pts[idx], np.nan)
        cov8 = np.where(found[:, None, None], cov[idx], np.nan)
        conf = np.where(found, score[idx] * naming.probability / max(naming.probability +
                                                                       naming.alternative.probability, 1e-9), 0.0)
        alt = naming.alternative
        alt_found = alt.visible & alt.matched
        alt_corners = np.where(alt_found[:, None], pts[np.maximum(alt.candidate, 0)], np.nan)
        return FrameDetection(corners, cov8, conf, found, alt_corners, float(alt.probability), naming.ambiguous,
                              box.astype(np.float64), pts)
