"""The naming's settings (NamingConfig): the noise, gates and weights name_corners fits the box with
(perception/naming.py), and the cues' weights its scoring uses (perception/naming_score.py)."""

from __future__ import annotations

from dataclasses import dataclass


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
    at most this many; max_corner_quads: with line cues, the three-corner faces tried (face_poses.corner_quads);
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
