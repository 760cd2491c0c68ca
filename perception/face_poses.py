"""Pose hypotheses from the box's faces: the candidate quadrilaterals a visible face may be (strictly convex
quadruples of candidates, and three candidates joined at a corner by verified lines completed to a parallelogram)
and the two planar poses (IPPE, from the face's homography: batched DLT, decomposed) that put a face's corners on
one. Pixels in the OpenCV convention; poses T to K as in perception/naming.py."""

from __future__ import annotations

import itertools

import numpy as np

from envisat_pose.geometry import TargetGeometry


def ordered_convex_quads(points: np.ndarray) -> np.ndarray:
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


def corner_quads(cand: np.ndarray, line_nll: np.ndarray, count: int) -> np.ndarray:
    """(L, 4, 2) quadrilaterals for faces of which only three corners were found: for the `count` candidate
    triples i-j-k best joined by verified lines at j (least line_nll[i, j] + line_nll[j, k]), the parallelogram
    i, j, k, i + k - j (the fourth corner as an affine view puts it; the refinement on the real candidates removes
    the perspective error), in increasing image angle as ordered_convex_quads orders them."""
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


def poses_from_faces(quads_px: np.ndarray, faces: np.ndarray, geometry: TargetGeometry,
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
