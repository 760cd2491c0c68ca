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
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import cv2
import numpy as np

from envisat_pose.geometry import EDGES, TargetGeometry, load_geometry, visible_corners
from envisat_pose.perception.heatmaps import CORNER_END, CORNER_JTYPE, N_JTYPES

_EDGE_ENDS = (np.array([a for a, _ in EDGES]), np.array([b for _, b in EDGES]))
HALF_TURNS = {"I": (1.0, 1.0, 1.0), "x": (1.0, -1.0, -1.0), "y": (-1.0, 1.0, -1.0), "z": (-1.0, -1.0, 1.0)}


@dataclass(frozen=True)
class NamingConfig:
    """sigma_px: candidate position noise, px; gate_px: a predicted corner farther than this from every candidate
    is missed (its cost saturates); coarse_gate_px: the same for the unrefined poses of single faces (a face's
    homography extrapolates its corners' noise to the far end); unexplained_weight: cost of a candidate no visible
    corner explains, in units of a corner at the gate (gate^2 / 2 sigma^2 nats); missed_weight: cost of a corner
    the pose shows but no candidate is near, in the same units (the network misses about one corner in five, so a
    miss is cheaper than a candidate left unexplained: a pose is not pushed to hide the corners the network
    missed by turning its face away); max_candidates: the best-scored candidates used; refine_top: hypotheses
    refined by LM; type_weight, line_weight: weights of the cues' negative log-probabilities (nats; the type
    head is under-confident: a temperature fitted per corner on held-out frames is ~3.4, but a frame's corners
    err together; at 2 the namings it settled were the half-turn in 2 of 420 held-out frames, with the shipped
    weights); ambiguity: the naming is flagged ambiguous when its half-turn alternative has at least this
    probability; prior_sigma_deg: spread of a prior pose's rotation; max_quads: with line cues, only the
    quadrilaterals whose 4 sides are best supported by the line verification (sum of -log p) are tried as faces,
    at most this many; max_corner_quads: with line cues, the three-corner faces tried (_corner_quads);
    relative_cues: the cues count as log-likelihood ratios against an uninformed guess (a type drawn among J, an
    edge at even odds), so that explaining one more candidate is not penalized by its cue's own cost (False: raw
    negative log-probabilities)."""

    sigma_px: float = 2.0
    gate_px: float = 6.0
    coarse_gate_px: float = 30.0
    unexplained_weight: float = 1.0
    missed_weight: float = 0.3
    max_candidates: int = 12
    refine_top: int = 30
    type_weight: float = 2.0
    line_weight: float = 1.0
    ambiguity: float = 0.1
    prior_sigma_deg: float = 30.0
    max_quads: int = 30
    max_corner_quads: int = 20
    relative_cues: bool = True


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


# per-geometry results of the functions below that depend on the geometry alone, computed once per geometry object
# (a naming asks for them every frame): {(function name, id(geometry)): (geometry, result)}
_GEOMETRY_CACHE: dict = {}


def _cached(name: str, geometry: TargetGeometry, compute):
    hit = _GEOMETRY_CACHE.get((name, id(geometry)))
    if hit is None or hit[0] is not geometry:
        hit = (geometry, compute(geometry))
        if len(_GEOMETRY_CACHE) > 64:
            _GEOMETRY_CACHE.clear()
        _GEOMETRY_CACHE[(name, id(geometry))] = hit
    return hit[1]


def symmetry_permutations(geometry: TargetGeometry) -> dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """For each half-turn g of HALF_TURNS: (perm (8,), S (3, 3), d (3,)) with corners[perm[k]] = S corners[k] + d:
    the pose (R S, t + R d) shows corner perm[k] where (R, t) shows corner k."""
    cached = _cached("symmetry_permutations", geometry, _symmetry_permutations)
    return {name: tuple(a.copy() for a in v) for name, v in cached.items()}


def _symmetry_permutations(geometry: TargetGeometry) -> dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    X = geometry.corners_T_m
    centre = X.mean(axis=0)
    out = {}
    for name, signs in HALF_TURNS.items():
        S = np.diag(signs)
        d = centre - S @ centre
        mapped = X @ S.T + d
        perm = np.argmin(np.linalg.norm(mapped[:, None, :] - X[None, :, :], axis=-1), axis=1)
        if sorted(perm) != list(range(8)) or not np.allclose(X[perm], mapped, atol=1e-6):
            raise ValueError(f"the box is not symmetric under the half-turn about {name}")
        out[name] = (perm, S, d)
    return out


def face_windings(geometry: TargetGeometry) -> np.ndarray:
    """(6, 4) corner indices of each face in the cyclic order of increasing image angle (y down) that every view
    from outside shows (perspective keeps a front-facing polygon's winding)."""
    return _cached("face_windings", geometry, _face_windings).copy()


def _face_windings(geometry: TargetGeometry) -> np.ndarray:
    X = geometry.corners_T_m
    out = []
    for k in range(6):
        idx = np.flatnonzero(geometry.face_corners[k])
        n = geometry.face_normals_T[k]
        # a camera on the outward normal looking back at the face: z_cam = -n, any x_cam in the face's plane
        z = -n
        x = np.cross(z, [0.0, 0.0, 1.0] if abs(z[2]) < 0.9 else [1.0, 0.0, 0.0])
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        R = np.stack([x, y, z])
        p = (X[idx] - X[idx].mean(axis=0)) @ R.T
        ang = np.arctan2(p[:, 1], p[:, 0])
        out.append(idx[np.argsort(ang)])
    return np.array(out)


def _ordered_convex_quads(points: np.ndarray) -> np.ndarray:
    """(Q, 4) index quadruples of points (M, 2) forming strictly convex quadrilaterals, in increasing angle
    about their centroid."""
    m = len(points)
    if m < 4:
        return np.zeros((0, 4), np.int64)
    combos = np.array(list(itertools.combinations(range(m), 4)))
    p = points[combos]  # (Q, 4, 2)
    c = p.mean(axis=1, keepdims=True)
    ang = np.arctan2(p[..., 1] - c[..., 1], p[..., 0] - c[..., 0])
    order = np.argsort(ang, axis=1)
    combos = np.take_along_axis(combos, order, axis=1)
    p = points[combos]
    e = np.roll(p, -1, axis=1) - p
    cross = e[:, :, 0] * np.roll(e, -1, axis=1)[:, :, 1] - e[:, :, 1] * np.roll(e, -1, axis=1)[:, :, 0]
    area = 0.5 * np.abs(np.sum(p[:, :, 0] * np.roll(p, -1, axis=1)[:, :, 1]
                               - p[:, :, 1] * np.roll(p, -1, axis=1)[:, :, 0], axis=1))
    convex = np.all(cross > 0, axis=1) & (area > 4.0)
    return combos[convex]


def _corner_quads(cand: np.ndarray, line_nll: np.ndarray, count: int) -> np.ndarray:
    """(L, 4, 2) quadrilaterals for faces of which only three corners were found: for the `count` candidate
    triples i-j-k best joined by verified lines at j (least line_nll[i, j] + line_nll[j, k]), the parallelogram
    i, j, k, i + k - j (the fourth corner as an affine view puts it; the refinement on the real candidates removes
    the perspective error), in increasing image angle as _ordered_convex_quads orders them."""
    m = len(cand)
    if m < 3 or count <= 0:
        return np.zeros((0, 4, 2))
    j, i, k = (a.ravel() for a in np.meshgrid(np.arange(m), np.arange(m), np.arange(m), indexing="ij"))
    ok = (i < k) & (i != j) & (k != j)
    j, i, k = j[ok], i[ok], k[ok]
    cost = line_nll[i, j] + line_nll[j, k]
    best = np.argsort(cost, kind="stable")[:count]
    pi, pj, pk = cand[i[best]], cand[j[best]], cand[k[best]]
    quad = np.stack([pi, pj, pk, pi + pk - pj], axis=1)
    a, b = pj - pi, pk - pj
    turn = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]
    quad = np.where((turn < 0)[:, None, None], quad[:, ::-1], quad)  # the winding of increasing angle (y down)
    area = np.abs(turn)  # the parallelogram's area, px^2
    return quad[area > 8.0]


def _homographies(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Exact homographies (N, 3, 3), h33 = 1, mapping src (N, 4, 2) to dst (N, 4, 2) (batched DLT)."""
    n = len(src)
    A = np.zeros((n, 8, 8))
    b = np.zeros((n, 8))
    x, y = src[..., 0], src[..., 1]
    u, v = dst[..., 0], dst[..., 1]
    A[:, 0::2, 0], A[:, 0::2, 1], A[:, 0::2, 2] = x, y, 1.0
    A[:, 0::2, 6], A[:, 0::2, 7] = -u * x, -u * y
    A[:, 1::2, 3], A[:, 1::2, 4], A[:, 1::2, 5] = x, y, 1.0
    A[:, 1::2, 6], A[:, 1::2, 7] = -v * x, -v * y
    b[:, 0::2], b[:, 1::2] = u, v
    ok = np.abs(np.linalg.det(A)) > 1e-12
    h = np.zeros((n, 8))
    h[ok] = np.linalg.solve(A[ok], b[ok][..., None])[..., 0]
    h[~ok] = np.nan
    return np.concatenate([h, np.ones((n, 1))], axis=1).reshape(n, 3, 3)


def _poses_from_faces(quads_px: np.ndarray, faces: np.ndarray, geometry: TargetGeometry,
                      K: np.ndarray, face_index: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The two IPPE poses (Collins and Bartoli 2014) putting face corners faces (N, 4) (indices into A-H) on
    quads_px (N, 4, 2): R (2N, 3, 3), t (2N, 3), solution s of hypothesis n at row 2 n + s. With face_index (N,),
    faces is a table (F, 4) and hypothesis n puts face faces[face_index[n]] on its quadrilateral (the faces' own
    frames are then computed once per face, not per hypothesis).

    A face lies in a plane of T: corners = o + X e1 + Y e2. The homography H of (X, Y) to normalized image
    coordinates has a Jacobian J at the face centre; in a camera turned so the centre's ray is its z axis
    (R_v), that Jacobian is B = (1 / d) (the top-left 2x2 block of the plane's rotation), d the centre's depth.
    The block's columns complete to orthonormal 3-vectors only with gamma = 1 / d = the largest singular value
    of B and a third row +-b, b b^T = I - B^T B / gamma^2: the two signs are planar pose's two solutions (the
    flip that a nearly affine view of a small face cannot settle; the other corners do)."""
    X = geometry.corners_T_m[faces]  # (N, 4, 3), or (F, 4, 3) with face_index
    o = X.mean(axis=1)
    e1 = X[:, 1] - X[:, 0]
    e1 /= np.linalg.norm(e1, axis=-1, keepdims=True)
    n = np.cross(X[:, 1] - X[:, 0], X[:, 2] - X[:, 1])
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    e2 = np.cross(n, e1)
    d = X - o[:, None, :]
    plane = np.stack([np.einsum("nki,ni->nk", d, e1), np.einsum("nki,ni->nk", d, e2)], axis=-1)
    E = np.stack([e1, e2, n], axis=-1)  # columns e1, e2, n
    if face_index is not None:
        o, plane, E = o[face_index], plane[face_index], E[face_index]
    Kinv = np.linalg.inv(K)
    norm = np.einsum("ij,nkj->nki", Kinv, np.concatenate([quads_px, np.ones(quads_px.shape[:2] + (1,))], -1))
    H = _homographies(plane, norm[..., :2] / norm[..., 2:])
    H = np.nan_to_num(H)
    h33 = np.where(np.abs(H[:, 2, 2]) > 1e-12, H[:, 2, 2], 1e-12)
    u0 = H[:, :2, 2] / h33[:, None]  # the centre's normalized image point
    J = (H[:, :2, :2] - u0[:, :, None] * H[:, 2:3, :2]) / h33[:, None, None]
    v = np.concatenate([u0, np.ones((len(u0), 1))], axis=1)
    s = np.linalg.norm(v, axis=1)
    v /= s[:, None]
    a1 = np.cross(np.array([0.0, 1.0, 0.0]), v)
    a1 /= np.linalg.norm(a1, axis=1, keepdims=True)
    Rv = np.stack([a1, np.cross(v, a1), v], axis=1)  # rows: R_v v = e_z
    B = (Rv[:, :2, :2] / s[:, None, None]) @ J
    BtB = np.transpose(B, (0, 2, 1)) @ B
    evals, evecs = np.linalg.eigh(BtB)  # ascending
    gamma = np.sqrt(np.maximum(evals[:, 1], 1e-18))
    b = np.sqrt(np.clip(1.0 - evals[:, 0] / gamma ** 2, 0.0, 1.0))[:, None] * evecs[:, :, 0]
    Rs, ts = [], []
    for sign in (1.0, -1.0):
        c12 = np.concatenate([B / gamma[:, None, None], sign * b[:, None, :]], axis=1)  # (N, 3, 2)
        Rp = np.concatenate([c12, np.cross(c12[:, :, 0], c12[:, :, 1])[:, :, None]], axis=2)
        Rp = _nearest_rotation(Rp)
        R = np.transpose(Rv, (0, 2, 1)) @ Rp @ np.transpose(E, (0, 2, 1))
        t = v / gamma[:, None] - np.einsum("nij,nj->ni", R, o)
        Rs.append(R)
        ts.append(t)
    return np.stack(Rs, axis=1).reshape(-1, 3, 3), np.stack(ts, axis=1).reshape(-1, 3)


def _nearest_rotation(M: np.ndarray, tol: float = 1e-12) -> np.ndarray:
    """The nearest rotation U V^T (SVD) of each matrix of M (N, 3, 3) whose columns are not orthonormal to tol;
    the others, rotations to rounding already (IPPE's columns are orthonormal by construction), as they are:
    they differ from their SVD's U V^T by rounding only, and a batched SVD costs most of the search's poses."""
    dev = np.abs(np.transpose(M, (0, 2, 1)) @ M - np.eye(3)).max(axis=(1, 2))
    off = ~(dev <= tol)  # NaN too
    if off.any():
        M = M.copy()
        U, _, Vt = np.linalg.svd(M[off])
        M[off] = U @ Vt
    return M


@dataclass(frozen=True)
class _Cues:
    type_nll: np.ndarray | None  # (M, 4) or (M, 2) -log p(type | candidate)
    line_nll: np.ndarray | None  # (M, M) -log p(edge | pair)


def _cost(d2: np.ndarray, dmin2: np.ndarray, vis: np.ndarray, inlier: np.ndarray, match: np.ndarray, cues: _Cues,
          cfg: NamingConfig, gate2: float, s2: float) -> np.ndarray:
    """_score's cost (N,) in nats of N poses from their squared distances d2 (N, 8, M) to the candidates."""
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


def _score(R: np.ndarray, t: np.ndarray, cand: np.ndarray, K: np.ndarray, cues: _Cues, geometry: TargetGeometry,
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


def _search(cand: np.ndarray, K: np.ndarray, cues: _Cues, g: TargetGeometry, cfg: NamingConfig,
            image_size: tuple[int, int] | None) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """The best hypotheses from the image alone: every face (24 namings of its corners) on every candidate
    quadrilateral, both planar poses each, scored with the coarse gate; (R (N, 3, 3), t (N, 3), match (N, 8)) of
    the refine_top best with a distinct association and at least 4 matched corners, or None."""
    line_nll = cues.line_nll
    quads = _ordered_convex_quads(cand)
    if line_nll is not None and len(quads) > cfg.max_quads:  # a face is a cycle of 4 verified lines
        sides = line_nll[quads, np.roll(quads, -1, axis=1)]
        quads = quads[np.argsort(sides.sum(axis=1), kind="stable")[: cfg.max_quads]]
    quads_px = cand[quads]
    if line_nll is not None and cfg.max_corner_quads > 0:  # faces seen by three corners only
        quads_px = np.concatenate([quads_px, _corner_quads(cand, line_nll, cfg.max_corner_quads)])
    if len(quads_px) == 0:
        return None
    windings = face_windings(g)
    rots = np.array([np.roll(np.arange(4), -r) for r in range(4)])
    faces = windings[:, rots].reshape(-1, 4)  # (24, 4): face f under rotation r
    qi = np.repeat(np.arange(len(quads_px)), len(faces))
    fi = np.tile(np.arange(len(faces)), len(quads_px))
    R, t = _poses_from_faces(quads_px[qi], faces, g, K, face_index=fi)  # two per assignment
    good = np.all(np.isfinite(R), axis=(1, 2)) & np.all(np.isfinite(t), axis=1) & (t[:, 2] > 0)
    R, t = R[good], t[good]
    if len(R) == 0:
        return None
    s = _score(R, t, cand, K, cues, g, cfg, image_size, cfg.coarse_gate_px, min_matches=4)
    enough = np.sum(s["match"] >= 0, axis=1) >= 4
    if not enough.any():
        return None
    order = np.flatnonzero(enough)[np.argsort(s["cost"][enough], kind="stable")]
    first = _first_of_each_row(s["match"][order])  # one hypothesis per association
    order = order[np.sort(first)][: cfg.refine_top]
    return R[order].copy(), t[order].copy(), s["match"][order]


def _from_prior(R: np.ndarray, t: np.ndarray, cand: np.ndarray, K: np.ndarray, cues: _Cues, g: TargetGeometry,
                cfg: NamingConfig, image_size: tuple[int, int] | None
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """A predicted pose (R_K_from_T (3, 3), t (3,) m) as the one hypothesis, associated with the coarse gate as
    the search's are: (R (1, 3, 3), t (1, 3), match (1, 8)), or None when it matches fewer than 4 corners (then
    the search runs)."""
    if not (np.all(np.isfinite(R)) and np.all(np.isfinite(t)) and t[2] > 0):
        return None
    s = _score(R[None], t[None], cand, K, cues, g, cfg, image_size, cfg.coarse_gate_px)
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
    cues = _Cues(type_nll, line_nll)
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


def _fit_box(cand: np.ndarray, K: np.ndarray, cues: _Cues, g: TargetGeometry, cfg: NamingConfig,
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
        sr = _score(Rr, tr, cand, K, cues, g, cfg, image_size, gate)
        match = sr["match"]
    best = int(np.argmin(sr["cost"]))  # the first of equals
    return Rr[best], tr[best]


def _symmetric_variants(Rb: np.ndarray, tb: np.ndarray, cand: np.ndarray, K: np.ndarray, cues: _Cues,
                        g: TargetGeometry, cfg: NamingConfig, image_size: tuple[int, int] | None,
                        prior_R: np.ndarray | None) -> tuple[dict, dict]:
    """The four symmetric namings of the fitted pose (Rb, tb): the same image, told apart only by the cues and,
    given, the prior attitude prior_R (a Gaussian in the angle between them, prior_sigma_deg). Returns
    ({name: (R, t, its score, log-probability)}, {name: probability})."""
    sym = symmetry_permutations(g)
    Rs = np.stack([Rb @ S for _, S, _ in sym.values()])
    ts = np.stack([tb + Rb @ d for _, _, d in sym.values()])
    s4 = _score(Rs, ts, cand, K, cues, g, cfg, image_size)  # the four at once (row by row: the same values)
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
