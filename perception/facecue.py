"""The half-turn's appearance cue: which face the image shows where a pose puts one, told from
the pixels inside it. Plain numpy + OpenCV (scipy's L-BFGS for the fit).

The box's corners cannot tell a pose from its half-turn about the long axis x (A<->C, B<->D, E<->G, F<->H): the
turn maps the +y face onto -y and +z onto -z (perception/naming.py). The faces carry covering classes
(geometry.FACE_COVERING: +y gold foil, -y black foil, +z silver foil, -z radiator, the ends painted panels), so
the region where a pose puts a face says which of its namings the image supports.

For a pose (R, t) each visible face is projected to its polygon; the polygon's interior (shrunk by `erode_px`)
gives FEATURES: brightness (absolute and against the brightest visible face), contrast, gradient energy, spread,
saturation, how much of the gradient runs along the face's edges (tiles, panels) rather than across (crinkled
foil), the region's size and its obliquity. A multinomial logistic regression on the standardized features and
their products, fitted on labelled frames, gives each region's class posterior P(c | region); divided by the
training set's class shares it is a likelihood up to a factor common to all classes.

A face region is the same image region under a pose and its half-turn; only the class the two namings expect of
it differs where it is a +-y or +-z face. The log-likelihood ratio of the pose against its half-turn is
    llr = sum over the visible faces r of [log L(c_pose(r) | r) - log L(c_turn(r) | r)],
divided by a temperature fitted on held-out frames (the regions of one frame err together). The cue abstains
(llr = 0) when the image does not look like this target under either naming: when, for the naming it favours,
some visible face's expected class has a posterior below `min_fit` (every face one covering, another
spacecraft's paint): a face cue that must pick between "gold" and "black" for a region that is neither would
decide the half-turn from nothing.
"""

from __future__ import annotations

import json
from dataclasses import dataclass

import cv2
import numpy as np

from envisat_pose.geometry import FACE_COVERING, FACE_NAMES, TargetGeometry

CLASS_NAMES = tuple(sorted(set(FACE_COVERING.values())))
FACE_CLASS = np.array([CLASS_NAMES.index(FACE_COVERING[f]) for f in FACE_NAMES])  # (6,) class of each face
# the face each face becomes under the half-turn about x: +-x stay, +y <-> -y, +z <-> -z
HALF_TURN_FACE = np.array([FACE_NAMES.index(f) for f in ("px", "mx", "my", "py", "mz", "pz")])
DARK_LEVEL, CLIPPED_LEVEL = 4.0, 248.0  # grey levels: a face whose median is outside them tells nothing
FEATURES = ("log_median", "log_median_vs_brightest", "contrast", "gradient", "spread", "saturated",
            "along_edges", "log_area", "obliquity")


@dataclass(frozen=True)
class FaceCue:
    """A fitted cue: the features' mean and std (F,), the softmax weights (1 + F + F (F + 1) / 2, C) over
    [1, z, z_i z_j (i <= j)] of the standardized features z, the training set's class shares (C,);
    temperature: the divisor of a frame's summed log-likelihood ratio; region_clip: the most one region's
    log-likelihood ratio counts (nats, before the temperature; fitted with it); min_fit: the least posterior of an
    expected class before the cue abstains; min_area_px, erode_px: the regions used."""

    mean: np.ndarray
    std: np.ndarray
    weights: np.ndarray
    class_share: np.ndarray
    temperature: float = 1.0
    region_clip: float = 3.0
    min_fit: float = 0.05
    min_area_px: float = 150.0
    erode_px: int = 2

    def to_json(self) -> str:
        return json.dumps({"mean": self.mean.tolist(), "std": self.std.tolist(), "weights": self.weights.tolist(),
                           "class_share": self.class_share.tolist(), "temperature": self.temperature,
                           "region_clip": None if np.isinf(self.region_clip) else self.region_clip, "min_fit": self.min_fit, "min_area_px": self.min_area_px, "erode_px": self.erode_px,
                           "features": list(FEATURES), "classes": list(CLASS_NAMES)}, sort_keys=True)

    @staticmethod
    def from_json(text: str | None) -> "FaceCue | None":
        """From the weights' metadata (`face_cue`); None for None or an empty string. ValueError when the JSON
        does not hold a cue of these features and classes."""
        if not text:
            return None
        raw = json.loads(text)
        if list(raw.get("features", [])) != list(FEATURES) or list(raw.get("classes", [])) != list(CLASS_NAMES):
            raise ValueError(f"face_cue: features {raw.get('features')} / classes {raw.get('classes')} differ from "
                             f"{list(FEATURES)} / {list(CLASS_NAMES)}")
        w = np.asarray(raw["weights"], float)
        n_f, n_c = len(FEATURES), len(CLASS_NAMES)
        if w.shape != (1 + n_f + n_f * (n_f + 1) // 2, n_c):
            raise ValueError(f"face_cue: weights of shape {w.shape}")
        return FaceCue(np.asarray(raw["mean"], float), np.asarray(raw["std"], float), w,
                       np.asarray(raw["class_share"], float), float(raw["temperature"]),
                       np.inf if raw["region_clip"] is None else float(raw["region_clip"]),
                       float(raw["min_fit"]), float(raw["min_area_px"]), int(raw["erode_px"]))


def face_polygons(R_cam_from_target: np.ndarray, t_cam_from_target_m: np.ndarray, K: np.ndarray,
                  geometry: TargetGeometry, windings: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each face's projected polygon (6, 4, 2) px (windings (6, 4) corner indices), whether it faces the camera
    (6,) bool, and the cosine between its outward normal and the direction to the camera at its centre (6,)."""
    R = np.asarray(R_cam_from_target, float)
    X = geometry.corners_T_m @ R.T + np.asarray(t_cam_from_target_m, float)
    z = np.maximum(X[:, 2:3], 1e-6)
    uv = (X[:, :2] / z) * np.diag(K)[:2] + np.asarray(K)[:2, 2]
    n_K = geometry.face_normals_T @ R.T
    centres = X[windings].mean(axis=1)
    to_cam = -centres / np.linalg.norm(centres, axis=1, keepdims=True)
    cos = np.sum(n_K * to_cam, axis=1)
    return uv[windings], cos > 0, cos


def region_features(image: np.ndarray, polygon_px: np.ndarray, cos_view: float, brightest: float,
                    erode_px: int, min_area_px: float) -> np.ndarray | None:
    """FEATURES (F,) of the image inside the polygon (4, 2) px shrunk by erode_px, or None when fewer than
    min_area_px pixels remain. brightest: the median grey level of the frame's brightest visible face."""
    h, w = image.shape
    lo = np.floor(polygon_px.min(axis=0)).astype(int) - 2
    hi = np.ceil(polygon_px.max(axis=0)).astype(int) + 3
    x0, y0 = max(lo[0], 0), max(lo[1], 0)
    x1, y1 = min(hi[0], w), min(hi[1], h)
    if x1 - x0 < 4 or y1 - y0 < 4:
        return None
    mask = np.zeros((y1 - y0, x1 - x0), np.uint8)
    cv2.fillPoly(mask, [np.round((polygon_px - [x0, y0]) * 16).astype(np.int32)], 1, lineType=cv2.LINE_8, shift=4)
    if erode_px > 0:
        mask = cv2.erode(mask, np.ones((2 * erode_px + 1, 2 * erode_px + 1), np.uint8))
    inside = mask.astype(bool)
    area = float(inside.sum())
    if area < min_area_px:
        return None
    patch = image[y0:y1, x0:x1].astype(np.float32)
    v = patch[inside]
    med = float(np.median(v))
    if med < DARK_LEVEL or med > CLIPPED_LEVEL:  # unlit or clipped: neither its brightness nor its texture shows
        return None
    p10, p90 = np.percentile(v, [10, 90])
    gx = cv2.Sobel(patch, cv2.CV_32F, 1, 0, ksize=3)[inside] / 8.0
    gy = cv2.Sobel(patch, cv2.CV_32F, 0, 1, ksize=3)[inside] / 8.0
    g2 = gx * gx + gy * gy
    along = 0.0  # the share of gradient energy across the face's edge directions (a tile grid, panel lines)
    if g2.sum() > 1e-6:
        c = []
        for e in (polygon_px[1] - polygon_px[0], polygon_px[2] - polygon_px[1]):
            u = e / max(float(np.linalg.norm(e)), 1e-9)
            n = np.array([-u[1], u[0]])
            c.append((gx * n[0] + gy * n[1]) ** 2)
        along = float(np.sum(np.maximum(c[0], c[1])) / g2.sum())
    scale = med + 4.0
    return np.array([np.log1p(med), np.log1p(med) - np.log1p(brightest), float(np.std(v)) / scale,
                     float(np.mean(np.sqrt(g2))) / scale, float(p90 - p10) / scale, float(np.mean(v >= 250)),
                     along, np.log(area), float(cos_view)])


def frame_regions(image: np.ndarray, R_cam_from_target: np.ndarray, t_cam_from_target_m: np.ndarray,
                  K: np.ndarray, geometry: TargetGeometry, windings: np.ndarray, erode_px: int = 2,
                  min_area_px: float = 150.0) -> list[tuple[int, np.ndarray]]:
    """The visible faces under the pose with enough pixels: (face index into FACE_NAMES, features (F,)) each."""
    poly, facing, cos = face_polygons(R_cam_from_target, t_cam_from_target_m, K, geometry, windings)
    feats = {}
    for k in np.flatnonzero(facing):
        f = region_features(image, poly[k], cos[k], 0.0, erode_px, min_area_px)
        if f is not None:
            feats[int(k)] = f
    brightest = max(float(np.expm1(f[0])) for f in feats.values()) if feats else 0.0
    out = []
    for k, f in feats.items():
        f = f.copy()
        f[1] = f[0] - np.log1p(brightest)
        out.append((k, f))
    return out


def design(z: np.ndarray) -> np.ndarray:
    """[1, z, z_i z_j (i <= j)] for standardized features z (N, F): (N, 1 + F + F (F + 1) / 2)."""
    z = np.atleast_2d(z)
    i, j = np.triu_indices(z.shape[1])
    return np.concatenate([np.ones((len(z), 1)), z, z[:, i] * z[:, j]], axis=1)


def log_softmax(a: np.ndarray) -> np.ndarray:
    return a - np.logaddexp.reduce(a, axis=-1, keepdims=True)


def fit_softmax(X: np.ndarray, y: np.ndarray, n_classes: int, l2: float = 1.0) -> np.ndarray:
    """Weights W (D, C) of P(c | x) = softmax(x W) minimizing the cross-entropy plus l2 |W[1:]|^2 / 2 (L-BFGS)."""
    from scipy.optimize import minimize

    Y = np.eye(n_classes)[y]
    reg = np.full((X.shape[1], 1), l2)
    reg[0] = 0.0

    def loss(w: np.ndarray) -> tuple[float, np.ndarray]:
        W = w.reshape(X.shape[1], n_classes)
        lp = log_softmax(X @ W)
        grad = X.T @ (np.exp(lp) - Y) + reg * W
        return float(-np.sum(Y * lp) + 0.5 * np.sum(reg * W * W)), grad.ravel()

    res = minimize(loss, np.zeros(X.shape[1] * n_classes), jac=True, method="L-BFGS-B", options={"maxiter": 2000})
    return res.x.reshape(X.shape[1], n_classes)


def fit_cue(regions: list[tuple[int, np.ndarray]], l2: float = 1.0, erode_px: int = 2,
            min_area_px: float = 150.0) -> FaceCue:
    """A FaceCue (temperature 1) from labelled regions (true face index, features)."""
    if not regions:
        raise ValueError("face cue: no face regions to fit")
    F = np.array([f for _, f in regions])
    y = FACE_CLASS[np.array([k for k, _ in regions])]
    counts = np.bincount(y, minlength=len(CLASS_NAMES))
    if np.any(counts < 10):
        raise ValueError(f"face cue: too few regions of some covering class ({dict(zip(CLASS_NAMES, counts.tolist()))})")
    mu, sd = F.mean(axis=0), F.std(axis=0) + 1e-9
    W = fit_softmax(design((F - mu) / sd), y, len(CLASS_NAMES), l2)
    return FaceCue(mu, sd, W, counts / counts.sum(), 1.0, np.inf, 0.05, min_area_px, erode_px)


def class_log_posterior(cue: FaceCue, features: np.ndarray) -> np.ndarray:
    """log P(c | region) (N, C) of regions' features (N, F)."""
    z = (np.atleast_2d(np.asarray(features, float)) - cue.mean) / cue.std
    return log_softmax(design(z) @ cue.weights)


def raw_llr(cue: FaceCue, regions: list[tuple[int, np.ndarray]]) -> tuple[float, bool]:
    """The summed log-likelihood ratio of a pose against its half-turn over its regions (no temperature), and
    whether the image fits this target under the naming it favours (every region's expected class at least
    min_fit; module doc). (0.0, False) without regions."""
    if not regions:
        return 0.0, False
    faces = np.array([k for k, _ in regions])
    lp = class_log_posterior(cue, np.array([f for _, f in regions]))
    ll = lp - np.log(cue.class_share)[None]  # log-likelihoods up to a per-region constant
    rows = np.arange(len(faces))
    c_pose, c_turn = FACE_CLASS[faces], FACE_CLASS[HALF_TURN_FACE[faces]]
    llr = float(np.sum(np.clip(ll[rows, c_pose] - ll[rows, c_turn], -cue.region_clip, cue.region_clip)))
    expected = c_pose if llr >= 0 else c_turn
    fits = bool(np.all(lp[rows, expected] >= np.log(cue.min_fit)))
    return llr, fits


def half_turn_llr(cue: FaceCue | None, image: np.ndarray, R_cam_from_target: np.ndarray,
                  t_cam_from_target_m: np.ndarray, K: np.ndarray, geometry: TargetGeometry,
                  windings: np.ndarray) -> float:
    """log P(image | the pose) - log P(image | its half-turn about x) from the faces' pixels, tempered; 0.0
    without a cue, without a usable face or where the image does not fit this target (module doc)."""
    if cue is None:
        return 0.0
    regions = frame_regions(image, R_cam_from_target, t_cam_from_target_m, K, geometry, windings, cue.erode_px,
                            cue.min_area_px)
    llr, fits = raw_llr(cue, regions)
    return llr / cue.temperature if fits else 0.0


TEMPERATURES = np.exp(np.linspace(np.log(0.05), np.log(50.0), 400))
REGION_CLIPS = (0.5, 1.0, 1.5, 2.0, 3.0, 4.0, 6.0, 10.0, np.inf)


def fit_temperature(llr: np.ndarray) -> tuple[float, float]:
    """The T > 0 minimizing the mean log loss of sigmoid(llr / T) for frames whose true pose is the one of llr
    (the frames the cue abstains on, llr = 0, left out), and that loss; (1, log 2) for none."""
    llr = np.asarray(llr, float)
    llr = llr[llr != 0.0]
    if len(llr) == 0:
        return 1.0, float(np.log(2.0))
    loss = [np.mean(np.logaddexp(0.0, -llr / t)) for t in TEMPERATURES]
    best = int(np.argmin(loss))
    return float(TEMPERATURES[best]), float(loss[best])


def decided_share(llr: np.ndarray, ambiguity: float) -> tuple[float, float]:
    """Of frames whose true pose has the (tempered) llr: the share the cue alone decides (the other naming below
    `ambiguity`) and the share it decides wrongly."""
    llr = np.asarray(llr, float)
    if len(llr) == 0:
        return float("nan"), float("nan")
    bound = np.log((1.0 - ambiguity) / ambiguity)
    return float(np.mean(np.abs(llr) > bound)), float(np.mean(llr < -bound))


def fit_and_temper(fit_frames: list[list], held_frames: list[list], l2: float = 1.0,
                   ambiguity: float = 0.1) -> tuple[FaceCue, dict]:
    """A FaceCue fitted on the regions of fit_frames (each a frame's frame_regions under its true pose) with the
    temperature fitted on held_frames; and its record on the held-out frames."""
    import dataclasses

    cue = fit_cue([r for f in fit_frames for r in f], l2)
    best = None
    for clip in REGION_CLIPS:  # the region clip and the temperature with the least held-out log loss
        c = dataclasses.replace(cue, region_clip=clip)
        held = [raw_llr(c, f) for f in held_frames if f]
        temperature, loss = fit_temperature(np.array([v for v, fits in held if fits]))
        if best is None or loss < best[0] - 1e-12:
            best = (loss, clip, temperature, held)
    _, clip, temperature, held = best
    cue = dataclasses.replace(cue, region_clip=clip, temperature=temperature)
    llr = np.array([v / temperature if fits else 0.0 for v, fits in held])
    decided, wrong = decided_share(llr, ambiguity)
    regions = [r for f in held_frames for r in f]
    acc = None
    if regions:
        pred = np.argmax(class_log_posterior(cue, np.array([f for _, f in regions])), axis=1)
        acc = float(np.mean(pred == FACE_CLASS[np.array([k for k, _ in regions])]))
    record = {"fit_regions": int(sum(len(f) for f in fit_frames)), "held_out_frames": len(held_frames),
              "held_out_frames_with_a_face": len(held), "temperature": temperature, "region_clip": clip,
              "held_out_region_class_accuracy": acc,
              "abstained_share": float(np.mean([not fits for _, fits in held])) if held else None,
              "right_share": float(np.mean(llr > 0)) if len(llr) else None,
              f"decided_share_at_{ambiguity:g}": decided, f"decided_wrong_share_at_{ambiguity:g}": wrong}
    return cue, record


def weigh_naming(naming, llr: float, ambiguity: float):
    """The naming (perception/naming.Naming) and its half-turn alternative re-weighed by the cue's log-likelihood
    ratio llr (the naming's pose against its half-turn): the pair keeps its probability mass, split by the
    naming's own odds times exp(llr); the likelier becomes the naming, and the result is ambiguous when the
    other keeps at least `ambiguity` of the whole."""
    import dataclasses

    alt = naming.alternative
    if alt is None or llr == 0.0:
        return naming
    mass = naming.probability + alt.probability
    log_odds = np.log(max(naming.probability, 1e-300)) - np.log(max(alt.probability, 1e-300)) + llr
    p_main = mass / (1.0 + float(np.exp(-np.clip(log_odds, -700.0, 700.0))))
    main = dataclasses.replace(naming, probability=p_main, alternative=None, ambiguous=False)
    other = dataclasses.replace(alt, probability=mass - p_main, alternative=None, ambiguous=False)
    if other.probability > main.probability:
        main, other = other, main
    return dataclasses.replace(main, alternative=other, ambiguous=bool(other.probability >= ambiguity))
