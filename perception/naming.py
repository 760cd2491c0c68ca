"""Name corner candidates A-H by fitting the known box wireframe: PnP with RANSAC over the assignments the box allows.

Plain numpy (and OpenCV) in and out: no torch here. Frames: T the target body frame (geometry.load_geometry),
camera frame K with x right, y down, z along the boresight; pixels in the OpenCV convention. A pose here is
(R_cam_from_target, t_cam_from_target_m), named as the shard labels name it: the same rotation and translation
as datagen's and the pipelines' (R_K_from_T, t_K_from_T_m), T to K.

Hypotheses: a convex quadrilateral of four candidates is one visible face of the box (a box seen from outside
always shows at least one face whole, but the network may miss one of its corners: three candidates joined at
a corner by verified lines also stand for a face, completed to a parallelogram), in the winding every visible
face keeps in the image, under each of its 4 rotations: 6 x 4 assignments per quadrilateral. Each gives a pose
from the face's homography (batched DLT, decomposed); all poses are scored at once by reprojection of the
corners they predict visible (a quadratic up to a gate; a visible corner with no candidate costs a miss),
candidates they leave unexplained, and, when given, junction-type and line-verification cues. The best few are
refined with cv2.solvePnP (iterative LM) on their inliers and scored again.

Symmetry: the box (half sizes a != b != c, centred) maps onto itself under the half-turns about x, y and z of T:
its corners alone cannot tell these 4 poses apart. The junction type's end (A-D at +x, E-H at the array's -x
end) separates the turns about y and z; the half-turn about the long axis x (A<->C, B<->D, E<->G, F<->H) is
settled by the type's side (+z or -z) where the image shows it, or by a prior pose (e.g. the filter's
prediction); otherwise both namings are returned with their probabilities and the result is flagged ambiguous.

This module is the fit (name_corners: search, refine, the symmetric namings) and its result (Naming); beside it
naming_config.py (NamingConfig), box_symmetry.py (the half-turns, the faces' windings), face_poses.py (the
quadrilaterals and their planar poses) and naming_score.py (a pose's cost against the candidates).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from envisat_pose.geometry import TargetGeometry, load_geometry
from envisat_pose.perception.box_symmetry import face_windings, symmetry_permutations
from envisat_pose.perception.face_poses import corner_quads, ordered_convex_quads, poses_from_faces
from envisat_pose.perception.naming_config import NamingConfig
from envisat_pose.perception.naming_score import Cues, score_poses


@dataclass(frozen=True)
class Naming:
    """A named box fit.

    corners_px: (8, 2) A-H: the matched candidate's pixel where one was matched, else the fitted projection.
    projected_px: (8, 2) the fitted pose's projection of A-H. visible: (8,) bool, the fitted pose's face test
    (and in the image when its size was given). matched: (8,) bool, a candidate was assigned; candidate: (8,) int,
    its index into the input candidates, -1 where none.
    R_cam_from_target (3, 3), t_cam_from_target_m (3,): the fitted pose. cost: the fit's cost (nats).
    probability: this naming's probability among the box's symmetric namings.
    alternative: the half-turn (about x) naming, with its own probability; ambiguous: the image (and the cues
    given) cannot settle between the two (alternative.probability >= config.ambiguity).
    """

    corners_px: np.ndarray
    projected_px: np.ndarray
    visible: np.ndarray
    matched: np.ndarray
    candidate: np.ndarray
    R_cam_from_target: np.ndarray
    t_cam_from_target_m: np.ndarray
    cost: float
    probability: float
    alternative: "Naming | None" = None
    ambiguous: bool = False


def _refine(R: np.ndarray, t: np.ndarray, match: np.ndarray, cand: np.ndarray, K: np.ndarray,
            geometry: TargetGeometry, robust_px: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """LM refinement (cv2.solvePnP, iterative from the guess) on the matched corners (at least 4); with
    robust_px, the matches farther than that from the guess's projection are left out first."""
    k = np.flatnonzero(match >= 0)
    if robust_px is not None and len(k) > 4:
        Xc = geometry.corners_T_m[k] @ R.T + t
        err = np.linalg.norm(Xc[:, :2] / Xc[:, 2:] * [K[0, 0], K[1, 1]] + K[:2, 2] - cand[match[k]], axis=1)
        near = err < robust_px
        if near.sum() >= 4:
            k = k[near]
    if len(k) < 4:
        return R, t
    rvec, _ = cv2.Rodrigues(R)
    ok, rvec, tvec = cv2.solvePnP(geometry.corners_T_m[k].astype(np.float64), cand[match[k]].astype(np.float64),
                                  K.astype(np.float64), None, rvec.copy(), t.reshape(3, 1).copy(),
                                  useExtrinsicGuess=True, flags=cv2.SOLVEPNP_ITERATIVE)
    if not ok or not np.all(np.isfinite(tvec)) or tvec[2, 0] <= 0:
        return R, t
    return cv2.Rodrigues(rvec)[0], tvec[:, 0]


def _rotation_angle_deg(Ra: np.ndarray, Rb: np.ndarray) -> float:
    c = (np.trace(Ra.T @ Rb) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def _first_of_each_row(rows: np.ndarray) -> np.ndarray:
    """The index of the first occurrence of each distinct row of rows (N, 8) of ints >= -1, in the order of
    np.unique(rows, axis=0, return_index=True) (each row packed into one integer: cheaper than unique's rows)."""
    base = int(rows.max(initial=-1)) + 2
    if base ** rows.shape[1] >= 2 ** 62:
        return np.unique(rows, axis=0, return_index=True)[1]
    code = np.zeros(len(rows), np.int64)
    for c in range(rows.shape[1]):  # the first column most significant: the rows' lexicographic order
        code = code * base + (rows[:, c] + 1)
    return np.unique(code, return_index=True)[1]


def _search(cand: np.ndarray, K: np.ndarray, cues: Cues, g: TargetGeometry, cfg: NamingConfig,
            image_size: tuple[int, int] | None) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """The best hypotheses from the image alone: every face (24 namings of its corners) on every candidate
    quadrilateral, both planar poses each, scored with the coarse gate; (R (N, 3, 3), t (N, 3), match (N, 8)) of
    the refine_top best with a distinct association and at least 4 matched corners, or None."""
    line_nll = cues.line_nll
    quads = ordered_convex_quads(cand)
    if line_nll is not None and len(quads) > cfg.max_quads:  # a face is a cycle of 4 verified lines
        sides = line_nll[quads, np.roll(quads, -1, axis=1)]
        quads = quads[np.argsort(sides.sum(axis=1), kind="stable")[: cfg.max_quads]]
    quads_px = cand[quads]
    if line_nll is not None and cfg.max_corner_quads > 0:  # faces seen by three corners only
        quads_px = np.concatenate([quads_px, corner_quads(cand, line_nll, cfg.max_corner_quads)])
    if len(quads_px) == 0:
        return None
    windings = face_windings(g)
    rots = np.array([np.roll(np.arange(4), -r) for r in range(4)])
    faces = windings[:, rots].reshape(-1, 4)  # (24, 4): face f under rotation r
    qi = np.repeat(np.arange(len(quads_px)), len(faces))
    fi = np.tile(np.arange(len(faces)), len(quads_px))
    R, t = poses_from_faces(quads_px[qi], faces, g, K, face_index=fi)  # two per assignment
    good = np.all(np.isfinite(R), axis=(1, 2)) & np.all(np.isfinite(t), axis=1) & (t[:, 2] > 0)
    R, t = R[good], t[good]
    if len(R) == 0:
        return None
    s = score_poses(R, t, cand, K, cues, g, cfg, image_size, cfg.coarse_gate_px, min_matches=4)
    enough = np.sum(s["match"] >= 0, axis=1) >= 4
    if not enough.any():
        return None
    order = np.flatnonzero(enough)[np.argsort(s["cost"][enough], kind="stable")]
    first = _first_of_each_row(s["match"][order])  # one hypothesis per association
    order = order[np.sort(first)][: cfg.refine_top]
    return R[order].copy(), t[order].copy(), s["match"][order]


def _from_prior(R: np.ndarray, t: np.ndarray, cand: np.ndarray, K: np.ndarray, cues: Cues, g: TargetGeometry,
                cfg: NamingConfig, image_size: tuple[int, int] | None
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """A predicted pose (R_K_from_T (3, 3), t (3,) m) as the one hypothesis, associated with the coarse gate as
    the search's are: (R (1, 3, 3), t (1, 3), match (1, 8)), or None when it matches fewer than 4 corners (then
    the search runs)."""
    if not (np.all(np.isfinite(R)) and np.all(np.isfinite(t)) and t[2] > 0):
        return None
    s = score_poses(R[None], t[None], cand, K, cues, g, cfg, image_size, cfg.coarse_gate_px)
    if np.sum(s["match"][0] >= 0) < 4:
        return None
    return R[None].copy(), t[None].copy(), s["match"]


def name_corners(points_px: np.ndarray, K: np.ndarray, score: np.ndarray | None = None,
                 type_prob: np.ndarray | None = None, edge_prob: np.ndarray | None = None,
                 image_size: tuple[int, int] | None = None, prior_R_cam_from_target: np.ndarray | None = None,
                 config: NamingConfig = NamingConfig(), geometry: TargetGeometry | None = None,
                 prior_t_cam_from_target_m: np.ndarray | None = None, prior_weighs_namings: bool = True
                 ) -> Naming | None:
    """Fit the box to unnamed junction candidates and name them.

    points_px: (M, 2) candidate pixels. K: (3, 3) intrinsics of the same image. score: (M,) detection scores
    (the best max_candidates are used; None: all, in the given order). type_prob: (M, 4) probability of each
    junction type (perception/heatmaps.py: end and side), or (M, 2) of the end only (+x: A-D, -x: E-H). edge_prob: (M, M) line-verification probability that candidates
    i, j are joined by a box edge. image_size: (width, height) px: corners predicted outside are not expected.
    prior_R_cam_from_target: (3, 3) a predicted attitude (R_K_from_T) that weighs the symmetric namings.
    prior_t_cam_from_target_m: (3,) m, with the attitude a predicted pose (T's origin in K): the fit starts from
    it alone instead of searching every face on every quadrilateral (a tracker's prediction; the search runs
    when the pose matches fewer than 4 candidates). prior_weighs_namings: False for a prior that only seeds the
    fit (a tracker whose hypotheses are still the pose and its symmetric twins: the symmetric namings'
    probabilities then come from the image's cues alone, never from the prior they are to test).
    Returns the best Naming (with its half-turn alternative) or None when no hypothesis explains 4 candidates.
    """
    g = geometry or load_geometry()
    cfg = config
    pts = np.asarray(points_px, dtype=np.float64).reshape(-1, 2)
    keep = np.flatnonzero(np.all(np.isfinite(pts), axis=1))
    if score is not None:
        keep = keep[np.argsort(-np.asarray(score)[keep], kind="stable")]
    keep = keep[: cfg.max_candidates]
    cand = pts[keep]
    eps = 1e-4
    type_nll = None if type_prob is None else -np.log(np.clip(np.asarray(type_prob, float)[keep], eps, 1.0))
    line_nll = None if edge_prob is None else -np.log(np.clip(np.asarray(edge_prob, float)[np.ix_(keep, keep)],
                                                              eps, 1.0))
    cues = Cues(type_nll, line_nll)
    fit = _fit_box(cand, K, cues, g, cfg, image_size, prior_R_cam_from_target, prior_t_cam_from_target_m)
    if fit is None:
        return None
    variants, prob = _symmetric_variants(*fit, cand, K, cues, g, cfg, image_size,
                                         prior_R_cam_from_target if prior_weighs_namings else None)
    top = max(variants, key=lambda n: prob[n])
    alt = {"I": "x", "x": "I", "y": "z", "z": "y"}[top]
    alternative = _naming(variants[alt], prob[alt], cand, keep)
    main = _naming(variants[top], prob[top], cand, keep)
    return Naming(**{**main.__dict__, "alternative": alternative, "ambiguous": bool(prob[alt] >= cfg.ambiguity)})


def _fit_box(cand: np.ndarray, K: np.ndarray, cues: Cues, g: TargetGeometry, cfg: NamingConfig,
             image_size: tuple[int, int] | None, prior_R: np.ndarray | None,
             prior_t_m: np.ndarray | None) -> tuple[np.ndarray, np.ndarray] | None:
    """The box's pose that best explains the candidates cand (M, 2) px: started from the prior pose (both given)
    or by the search over faces and quadrilaterals, refined and re-associated twice (a gate of 2 gate_px, then
    gate_px). Returns (R_cam_from_target (3, 3), t_cam_from_target_m (3,)) of the least cost, or None when no
    hypothesis explains 4 candidates."""
    start = None
    if prior_R is not None and prior_t_m is not None:
        start = _from_prior(np.asarray(prior_R, float), np.asarray(prior_t_m, float), cand, K, cues, g, cfg,
                            image_size)
    if start is None:
        start = _search(cand, K, cues, g, cfg, image_size)
    if start is None:
        return None
    Rr, tr, match = start
    for step, gate in enumerate((2 * cfg.gate_px, cfg.gate_px)):  # refine, re-associate with a tighter gate
        for n in range(len(Rr)):
            Rr[n], tr[n] = _refine(Rr[n], tr[n], match[n], cand, K, g,
                                   robust_px=cfg.coarse_gate_px / 4 if step == 0 else None)
        sr = score_poses(Rr, tr, cand, K, cues, g, cfg, image_size, gate)
        match = sr["match"]
    best = int(np.argmin(sr["cost"]))  # the first of equals
    return Rr[best], tr[best]


def _symmetric_variants(Rb: np.ndarray, tb: np.ndarray, cand: np.ndarray, K: np.ndarray, cues: Cues,
                        g: TargetGeometry, cfg: NamingConfig, image_size: tuple[int, int] | None,
                        prior_R: np.ndarray | None) -> tuple[dict, dict]:
    """The four symmetric namings of the fitted pose (Rb, tb): the same image, told apart only by the cues and,
    given, the prior attitude prior_R (a Gaussian in the angle between them, prior_sigma_deg). Returns
    ({name: (R, t, its score, log-probability)}, {name: probability})."""
    sym = symmetry_permutations(g)
    Rs = np.stack([Rb @ S for _, S, _ in sym.values()])
    ts = np.stack([tb + Rb @ d for _, _, d in sym.values()])
    s4 = score_poses(Rs, ts, cand, K, cues, g, cfg, image_size)  # the four at once (row by row: the same values)
    variants = {}
    for n, name in enumerate(sym):
        Rg, tg = Rs[n], ts[n]
        sg = {k: v[n:n + 1] for k, v in s4.items()}
        logp = -sg["cost"][0]
        if prior_R is not None:
            ang = _rotation_angle_deg(prior_R, Rg)
            logp -= 0.5 * (ang / cfg.prior_sigma_deg) ** 2
        variants[name] = (Rg, tg, sg, logp)
    logps = np.array([v[3] for v in variants.values()])
    probs = np.exp(logps - logps.max())
    probs /= probs.sum()
    return variants, dict(zip(variants, probs))


def _naming(variant: tuple, prob: float, cand: np.ndarray, keep: np.ndarray) -> Naming:
    """One symmetric naming as a Naming: matched corners at their candidates, the others where projected; keep
    maps the candidates back to the caller's indices."""
    Rg, tg, sg, _ = variant
    match = sg["match"][0]
    proj = sg["projected"][0]
    corners = np.where((match >= 0)[:, None], cand[np.maximum(match, 0)], proj)
    return Naming(corners, proj, sg["visible"][0], match >= 0, np.where(match >= 0, keep[np.maximum(match, 0)], -1),
                  Rg, tg, float(sg["cost"][0]), float(prob))
