"""Scoring poses of the box against unnamed corner candidates: each pose's projected corners matched to the
candidates within a gate, its cost in nats from the reprojection (a quadratic up to the gate; a visible corner
with no candidate costs a miss), the candidates it leaves unexplained and, when given, the junction-type and
line-verification cues (Cues)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from envisat_pose.geometry import EDGES, TargetGeometry, visible_corners
from envisat_pose.perception.heatmaps import CORNER_END, CORNER_JTYPE, N_JTYPES
from envisat_pose.perception.naming_config import NamingConfig

_EDGE_ENDS = (np.array([a for a, _ in EDGES]), np.array([b for _, b in EDGES]))


@dataclass(frozen=True)
class Cues:
    """The candidates' cues as negative log-probabilities (None: not given)."""

    type_nll: np.ndarray | None  # (M, 4) or (M, 2) -log p(type | candidate)
    line_nll: np.ndarray | None  # (M, M) -log p(edge | pair)


def _cost(d2: np.ndarray, dmin2: np.ndarray, vis: np.ndarray, inlier: np.ndarray, match: np.ndarray, cues: Cues,
          cfg: NamingConfig, gate2: float, s2: float) -> np.ndarray:
    """score_poses' cost (N,) in nats of N poses from their squared distances d2 (N, 8, M) to the candidates."""
    cost = np.sum(np.where(inlier, dmin2, np.where(vis, cfg.missed_weight * gate2, 0.0)), axis=1) / (2 * s2)
    near = d2 < gate2
    near &= vis[:, :, None]
    explained = np.any(near, axis=1)  # (N, M)
    cost += cfg.unexplained_weight * gate2 / (2 * s2) * np.sum(~explained, axis=1)
    if cues.type_nll is not None:
        jt = CORNER_JTYPE if cues.type_nll.shape[1] == N_JTYPES else CORNER_END
        # relative to a type drawn at random (log J): a confident right type lowers the cost, so explaining one
        # more candidate is not penalized for the cue itself
        nll = cues.type_nll[np.where(match >= 0, match, 0), jt[None, :]]
        nll = nll - cfg.relative_cues * np.log(cues.type_nll.shape[1])
        cost += cfg.type_weight * np.sum(np.where(match >= 0, nll, 0.0), axis=1)
    if cues.line_nll is not None:
        ea, eb = _EDGE_ENDS
        ma, mb = match[:, ea], match[:, eb]  # (N, 12) the candidates at each edge's ends
        ok = (ma >= 0) & (mb >= 0) & (ma != mb)
        nll = cues.line_nll[np.maximum(ma, 0), np.maximum(mb, 0)] - cfg.relative_cues * np.log(2.0)
        term = cfg.line_weight * np.where(ok, nll, 0.0)
        for e in range(len(ea)):  # edge by edge, in EDGES' order (the same sums as ever)
            cost += term[:, e]
    return cost


def score_poses(R: np.ndarray, t: np.ndarray, cand: np.ndarray, K: np.ndarray, cues: Cues, geometry: TargetGeometry,
           cfg: NamingConfig, image_size: tuple[int, int] | None, gate_px: float | None = None,
           min_matches: int = 0) -> dict[str, np.ndarray]:
    """Score N poses against M candidates with a gate of gate_px (default cfg.gate_px). Returns cost (N,) in
    nats and, per pose, visible (N, 8), match (N, 8) candidate index or -1, projected (N, 8, 2). min_matches:
    the cost of a pose that matches fewer corners is inf (not computed)."""
    Xc = np.matmul(R, geometry.corners_T_m.T).transpose(0, 2, 1) + t[:, None, :]  # (N, 8, 3) corners in K
    front = Xc[..., 2] > 1e-3
    proj = np.einsum("ij,nkj->nki", K, Xc)
    proj = proj[..., :2] / np.where(front, proj[..., 2], 1.0)[..., None]
    c_T = -np.einsum("nji,nj->ni", R, t)  # camera centre in T
    vis = visible_corners(c_T, geometry) & front
    if image_size is not None:
        w, h = image_size
        vis &= (proj[..., 0] > -0.5) & (proj[..., 0] < w - 0.5) & (proj[..., 1] > -0.5) & (proj[..., 1] < h - 0.5)
    dx = proj[:, :, None, 0] - cand[None, None, :, 0]
    dy = proj[:, :, None, 1] - cand[None, None, :, 1]
    d2 = dx * dx  # (N, 8, M) squared distances
    d2 += dy * dy
    if np.isnan(proj).any():
        d2[np.isnan(d2)] = np.inf
    j = np.argmin(d2, axis=2)
    dmin2 = np.take_along_axis(d2, j[..., None], axis=2)[..., 0]
    gate2 = (gate_px or cfg.gate_px) ** 2
    s2 = cfg.sigma_px ** 2 * (gate2 / cfg.gate_px ** 2)
    inlier = vis & (dmin2 < gate2)
    match = np.where(inlier, j, -1)
    if min_matches:  # the cost only where it is asked for (row by row: the same values)
        rows = np.flatnonzero(np.sum(inlier, axis=1) >= min_matches)
        cost = np.full(len(R), np.inf)
        cost[rows] = _cost(d2[rows], dmin2[rows], vis[rows], inlier[rows], match[rows], cues, cfg, gate2, s2)
    else:
        cost = _cost(d2, dmin2, vis, inlier, match, cues, cfg, gate2, s2)
    return {"cost": cost, "visible": vis, "match": match, "projected": proj}
