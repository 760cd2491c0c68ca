"""The namings a tracker hypothesis may give a frame's keypoints: the detector's own, and its renaming by each
symmetry of the target's keypoint set that something could tell apart.

A symmetry (S, d) maps the keypoint set onto itself: keypoint perm[k] = S keypoint k + d (in T, m). Its keypoints
alone cannot tell the pose (R, t) from (R S, t + R d), so a detector's names may be off by it, and a cold start
fits one hypothesis per naming (pipelines/tracking/acquisition.py). What settles them: the image where the shape
or the materials break the symmetry (the detector's names, and ENVISAT's half-turn probability), the dynamics
where the inertia does (a rotation that does not map the inertia tensor onto itself changes the torque-free
motion). A symmetry that nothing breaks (shape, materials and inertia all keep it: the CubeSat's half-turns) gives
poses that no image and no motion ever tell apart: they are one pose of the target, not two hypotheses, and a
score compares an estimate with the truth up to them (`equivalent`).

Two kinds, by the detector:
- ENVISAT's corner network (`box_namings`): the box's half-turns about x, y and z (perception/box_symmetry.py),
  the detector's half-turn probability speaking of the long-axis one; exactly the tracker's namings before
  targets existed.
- a keypoint network trained with `envisat train --target` (`target_namings`): the Target's symmetries, one
  per class of poses that something tells apart. The network names twins its materials keep by chance (its loss
  takes the smallest over them), the others as it learned: a renaming by a symmetry the image breaks costs the
  least the detector ever concedes per look (log clip), one the image keeps nothing.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from envisat_pose.attitude import dcm_to_mrp, mrp_to_dcm
from envisat_pose.geometry import load_geometry
from envisat_pose.perception.box_symmetry import symmetry_permutations
from envisat_pose.state import MRP, POS, RATE

INERTIA_RTOL = 1e-3  # a rotation keeps the inertia when S J S^T = J within this share of J's largest entry
SAME_ROTATION_TOL = 1e-6  # two rotations are one when their matrices agree within this
# ENVISAT's corner network's namings: the detector's own, then its renaming by the box's half-turn about x (the
# long axis, the one the detector's half-turn probability speaks of), y and z
BOX_NAMES = ("detector", "x", "y", "z")


def renamed_state(x: np.ndarray, S: np.ndarray, d: np.ndarray) -> np.ndarray:
    """The same physical pose described in the naming of the symmetry (S (3, 3), d (3,) m; keypoint perm[k] = S
    keypoint k + d, Namings): keypoint k of T' sits where keypoint perm[k] of T does, so Gamma'^T X_k = Gamma^T
    (S X_k + d): T' has Gamma' = S^T Gamma, its origin moved by d (rho' = rho + Gamma^T d) and w' = S^T w. (A
    half-turn is its own inverse; a quarter-turn was applied the other way round before, S Gamma, so its
    hypothesis met its renamed keypoints 90 deg off and never fitted.) (..., 12) -> a new array."""
    x = np.array(x, dtype=float)
    G = mrp_to_dcm(x[..., MRP])
    x[..., POS] = x[..., POS] + np.einsum("...ji,j->...i", G, d)
    x[..., MRP] = dcm_to_mrp(np.einsum("ji,...jk->...ik", S, G))
    x[..., RATE] = x[..., RATE] @ S
    return x


@dataclass(frozen=True)
class Namings:
    """names (N,): "detector" first, then one per symmetry; perms (N, K) int, row 0 the identity; S (N, 3, 3) and
    d (N, 3) m with keypoint perms[n][k] = S[n] keypoint k + d[n]; image_tells (N,) bool: the shape or the
    materials break naming n's symmetry, so the detector's own names speak against it; half_turn_prob: naming 1
    is the half-turn the detector's alt_probability speaks of (ENVISAT's corner network); equivalent (E, 3, 3):
    the rotations about the centre of mass that nothing breaks (the pose is defined up to them; empty: none).
    relabel_perms (R, K), relabel_S (R, 3, 3), relabel_d (R, 3), relabel_class (R,): every relabeling a frame's
    keypoints may need to agree with a hypothesis, each naming composed with each equivalent rotation (the
    identity first), and the naming it belongs to: a network names twins that nothing breaks by chance, frame by
    frame, and such a relabeling is no other hypothesis. Without equivalents they are the namings themselves."""

    names: tuple[str, ...]
    perms: np.ndarray
    S: np.ndarray
    d: np.ndarray
    image_tells: np.ndarray
    half_turn_prob: bool
    equivalent: np.ndarray
    relabel_perms: np.ndarray
    relabel_S: np.ndarray
    relabel_d: np.ndarray
    relabel_class: np.ndarray

    @property
    def count(self) -> int:
        return len(self.names)

    @property
    def num_keypoints(self) -> int:
        return int(self.perms.shape[1])

    @property
    def relabel_count(self) -> int:
        return int(self.relabel_perms.shape[0])

    def relabeled(self, z_px: np.ndarray, cov_px: np.ndarray, r: int) -> tuple[np.ndarray, np.ndarray]:
        """Keypoints (K, 2) and covariances (K, 2, 2) under relabeling r (renamed's rule)."""
        return (z_px, cov_px) if r == 0 else (z_px[self.relabel_perms[r]], cov_px[self.relabel_perms[r]])

    def relabeled_state(self, x: np.ndarray, r: int) -> np.ndarray:
        """The same physical pose described under relabeling r (renamed_state). (..., 12)."""
        return np.array(x, dtype=float) if r == 0 else renamed_state(x, self.relabel_S[r], self.relabel_d[r])

    def renamed(self, z_px: np.ndarray, cov_px: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
        """Keypoints (K, 2) and covariances (K, 2, 2) under naming n: keypoint k takes keypoint perms[n][k]."""
        if n == 0:
            return z_px, cov_px
        return z_px[self.perms[n]], cov_px[self.perms[n]]

    def state(self, x: np.ndarray, n: int) -> np.ndarray:
        """The same physical pose described in naming n (renamed_state with S[n], d[n]). (..., 12)."""
        return np.array(x, dtype=float) if n == 0 else renamed_state(x, self.S[n], self.d[n])

    def log_likelihood(self, p_alt: float, n: int, clip: float) -> float:
        """The detector's appearance log-likelihood of naming n in one look. ENVISAT's corner network: log(1 - p)
        for its own naming, log(p) for the long-axis half-turn (p its half-turn probability clipped to
        [clip, 1 - clip]), log(clip) for the y and z half-turns, on which it gives no probability (possible, but
        only the geometry and the dynamics can make them win). A keypoint network: 0 for its own naming and for a
        renaming the image cannot tell, log(clip) for one the image tells."""
        if self.half_turn_prob:
            p = float(np.clip(p_alt, clip, 1.0 - clip))
            return float(np.log1p(-p)) if n == 0 else float(np.log(p)) if n == 1 else float(np.log(clip))
        return float(np.log(clip)) if n > 0 and self.image_tells[n] else 0.0

    def aligned_p_alt(self, p_alt: float, n: int) -> float:
        """A frame's half-turn probability once the frame is renamed by naming n: 1 - p under the half-turn it
        speaks of, 0.5 under the others (about which it says nothing); kept by a keypoint network's namings."""
        if not self.half_turn_prob:
            return p_alt
        return 1.0 - p_alt if n == 1 else 0.5 if n > 1 else p_alt


@functools.lru_cache(maxsize=1)
def box_namings() -> Namings:
    """ENVISAT's corner network's namings: the detector's, and its renaming by the box's half-turns about x (the
    long axis, the one its half-turn probability speaks of), y and z (box_symmetry.symmetry_permutations of the
    MJCF's box). Computed once; not to be modified."""
    syms = symmetry_permutations(load_geometry())
    names = BOX_NAMES
    perms = np.stack([np.arange(8)] + [np.asarray(syms[n][0]) for n in names[1:]])
    S = np.stack([np.eye(3)] + [np.asarray(syms[n][1], float) for n in names[1:]])
    d = np.stack([np.zeros(3)] + [np.asarray(syms[n][2], float) for n in names[1:]])
    return _frozen(Namings(names, perms, S, d, np.ones(4, bool), True, np.zeros((0, 3, 3)), perms.copy(), S.copy(),
                           d.copy(), np.arange(4)))


def inertia_keeps(R_T: np.ndarray, J_T: np.ndarray) -> bool:
    """Whether the rotation R_T (3, 3) maps the inertia tensor J_T (3, 3) onto itself (INERTIA_RTOL): then the
    torque-free motion cannot tell a pose from its twin by R_T."""
    J = np.asarray(J_T, float)
    return bool(np.max(np.abs(R_T @ J @ R_T.T - J)) <= INERTIA_RTOL * np.max(np.abs(J)))


def target_namings(target, J_T: np.ndarray) -> Namings:
    """A keypoint network's namings of the Target `target` whose filter takes the inertia J_T (3, 3) kg m^2: the
    detector's own, then one per class of its symmetries (target.symmetries, rotations about the centre of mass)
    that something breaks, classes taken modulo the symmetries nothing breaks (equivalent: shape, materials and
    J_T all keep them), so that no two hypotheses are poses nothing could tell apart."""
    K = target.num_keypoints
    nothing = [s for s in target.symmetries if not s.broken_by and inertia_keeps(s.R_T, J_T)]
    equivalent = [np.eye(3)] + [np.asarray(s.R_T, float) for s in nothing]
    names, perms, S, tells = ["detector"], [np.arange(K)], [np.eye(3)], [False]
    for s in target.symmetries:
        R = np.asarray(s.R_T, float)
        if any(np.allclose(Rr.T @ R, E, atol=SAME_ROTATION_TOL) for Rr in S for E in equivalent):
            continue  # the identity's class or one already taken: the same pose as far as anything can tell
        axis = np.round(np.asarray(s.axis_T, float), 3)
        names.append(f"{s.angle_deg:g} deg about ({axis[0]:g}, {axis[1]:g}, {axis[2]:g})")
        perms.append(np.asarray(s.perm, int))
        S.append(R)
        tells.append(bool(s.broken_by))
    X = np.asarray(target.keypoints_T_m, float)
    relabel = [(c, Sn @ E) for c, Sn in enumerate(S) for E in equivalent]  # each naming, then its equivalents
    return _frozen(Namings(tuple(names), np.stack(perms), np.stack(S), np.zeros((len(S), 3)), np.array(tells),
                           False, np.stack(equivalent[1:]) if nothing else np.zeros((0, 3, 3)),
                           np.stack([rotation_perm(R, X, target.reach_m) for _, R in relabel]),
                           np.stack([R for _, R in relabel]), np.zeros((len(relabel), 3)),
                           np.array([c for c, _ in relabel])))


def rotation_perm(R_T: np.ndarray, keypoints_T_m: np.ndarray, reach_m: float) -> np.ndarray:
    """(K,) int: the permutation a rotation of the keypoint set's symmetry group makes, R_T keypoint k = keypoint
    perm[k] (to 1e-3 of the reach: the group's own products, not a new symmetry)."""
    mapped = keypoints_T_m @ R_T.T
    dist = np.linalg.norm(mapped[:, None, :] - keypoints_T_m[None, :, :], axis=-1)
    perm = np.argmin(dist, axis=1)
    if sorted(perm.tolist()) != list(range(len(perm))) or dist[np.arange(len(perm)), perm].max() > 1e-3 * reach_m:
        raise ValueError("a product of the target's symmetries does not map its keypoints onto themselves")
    return perm


def _frozen(n: Namings) -> Namings:
    for a in (n.perms, n.S, n.d, n.image_tells, n.equivalent, n.relabel_perms, n.relabel_S, n.relabel_d,
              n.relabel_class):
        a.setflags(write=False)
    return n
