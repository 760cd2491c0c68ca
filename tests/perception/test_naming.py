"""Naming by fitting the box: ground-truth geometry through the project camera, no network."""

import collections
import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(__file__))
from naming_cases import make_case, outcome  # noqa: E402

from envisat_pose.geometry import load_geometry  # noqa: E402
from envisat_pose.perception.box_symmetry import face_windings, symmetry_permutations  # noqa: E402
from envisat_pose.perception.face_poses import poses_from_faces  # noqa: E402
from envisat_pose.perception.naming import name_corners  # noqa: E402
from envisat_pose.perception.naming_config import NamingConfig  # noqa: E402


def test_face_poses_exact_without_noise():
    """Both planar solutions are computed; one of them is the true pose to rounding."""
    g = load_geometry()
    rng = np.random.default_rng(1)
    n = 0
    for _ in range(30):
        case = make_case(rng, noise_px=0.0, n_spurious=0)
        for q in face_windings(g):
            if case["visible"][q].all():
                R, t = poses_from_faces(case["corners_px"][q][None], q[None], g, case["K"])
                err = min(np.abs(Ri - case["R"]).max() + np.abs(ti - case["t"]).max() for Ri, ti in zip(R, t))
                assert err < 1e-6
                n += 1
    assert n > 30


def test_half_turns_map_corners():
    g = load_geometry()
    perm = symmetry_permutations(g)["x"][0]
    assert "".join("ABCDEFGH"[k] for k in perm) == "CDABGHEF"


def test_naming_recovers_names_or_flags_the_half_turn():
    """Shuffled visible corners with 1 px noise, 2 spurious junctions, junction types right at 85 % (5 % flipped):
    the true names, or the half-turn pair flagged ambiguous, in nearly all cases."""
    rng = np.random.default_rng(2)
    counts = collections.Counter()
    n = 150
    for _ in range(n):
        case = make_case(rng)
        naming = name_corners(case["points_px"], case["K"], type_prob=case["type_prob"],
                              image_size=case["image_size"])
        counts[outcome(case, naming)] += 1
    print(dict(counts))
    assert counts["wrong"] <= 0.05 * n
    assert counts["right"] > 0.3 * n and counts["ambiguous"] > 0.3 * n  # the half-turn is ambiguous, both ways


def test_prior_pose_settles_the_half_turn():
    rng = np.random.default_rng(3)
    settled = 0
    for _ in range(30):
        case = make_case(rng)
        naming = name_corners(case["points_px"], case["K"], type_prob=case["type_prob"],
                              image_size=case["image_size"], prior_R_cam_from_target=case["R"])
        if outcome(case, naming) == "right" and not naming.ambiguous:
            settled += 1
    assert settled >= 27


def test_prior_pose_start_names_as_the_search_does():
    """A tracker's predicted pose (a little off the truth) as the start instead of the face search: the same
    names and pose as the search on every case, nearly all right with the half-turn settled; a prior that matches
    nothing falls back to the search."""
    rng = np.random.default_rng(4)
    right = 0
    for _ in range(30):
        case = make_case(rng)
        nudge = np.array([[1.0, -0.01, 0.0], [0.01, 1.0, 0.0], [0.0, 0.0, 1.0]])  # ~0.6 deg off
        R_prior = nudge @ case["R"]
        t_prior = case["t"] + rng.normal(scale=0.05, size=3)
        kw = dict(type_prob=case["type_prob"], image_size=case["image_size"], prior_R_cam_from_target=R_prior)
        searched = name_corners(case["points_px"], case["K"], **kw)
        started = name_corners(case["points_px"], case["K"], prior_t_cam_from_target_m=t_prior, **kw)
        right += outcome(case, started) == "right" and not started.ambiguous
        assert np.array_equal(started.candidate, searched.candidate)
        assert np.allclose(started.R_cam_from_target, searched.R_cam_from_target, atol=1e-6)
        far = name_corners(case["points_px"], case["K"], prior_t_cam_from_target_m=t_prior + [50.0, 0.0, 0.0], **kw)
        assert np.array_equal(far.candidate, searched.candidate)
    assert right >= 27


def test_a_prior_behind_the_camera_is_not_a_start():
    """The box's corners are point-symmetric about its origin (checked here), so the pose (R, -t) puts every
    corner at minus a true one's camera point: each projects exactly onto a true corner's pixel, all behind the
    camera. Such a prior is no pose: the fit falls back to the search, in front (the prior's own depth test and
    the scoring's front test each lead there; the test fails with both removed)."""
    g = load_geometry()
    X = g.corners_T_m
    assert np.allclose(np.sort(-X, axis=0), np.sort(X, axis=0)) and all(
        np.min(np.linalg.norm(X + x, axis=1)) < 1e-9 for x in X)
    rng = np.random.default_rng(6)
    for _ in range(5):
        case = make_case(rng)
        kw = dict(type_prob=case["type_prob"], image_size=case["image_size"], prior_R_cam_from_target=case["R"])
        searched = name_corners(case["points_px"], case["K"], **kw)
        behind = name_corners(case["points_px"], case["K"], prior_t_cam_from_target_m=-case["t"], **kw)
        assert behind.t_cam_from_target_m[2] > 0
        assert np.array_equal(behind.candidate, searched.candidate)
        assert np.allclose(behind.R_cam_from_target, searched.R_cam_from_target, atol=1e-6)


def test_a_seeding_prior_leaves_the_half_turn_to_the_image():
    """A prior that only seeds the fit (prior_weighs_namings=False), here the true pose's half-turn twin (a
    tracker's bank before it has decided): the same names and half-turn probabilities as the search without any
    prior, where a weighing prior pulls the naming to the twin it was given."""
    rng = np.random.default_rng(6)
    _, S, d = symmetry_permutations(load_geometry())["x"]
    pulled = 0
    for _ in range(30):
        case = make_case(rng)
        R_twin, t_twin = case["R"] @ S, case["t"] + case["R"] @ d
        kw = dict(type_prob=case["type_prob"], image_size=case["image_size"])
        free = name_corners(case["points_px"], case["K"], **kw)
        seeded = name_corners(case["points_px"], case["K"], prior_R_cam_from_target=R_twin,
                              prior_t_cam_from_target_m=t_twin, prior_weighs_namings=False, **kw)
        weighed = name_corners(case["points_px"], case["K"], prior_R_cam_from_target=R_twin,
                               prior_t_cam_from_target_m=t_twin, **kw)
        def pair(n):  # the naming and its half-turn: names -> probability (which of equals leads is arbitrary)
            return {tuple(m.candidate): round(m.probability, 6) for m in (n, n.alternative)}

        assert pair(seeded) == pair(free)
        pulled += outcome(case, weighed) == "wrong" or weighed.probability < free.probability - 1e-6 \
            or not np.allclose(weighed.corners_px, free.corners_px, equal_nan=True)
    assert pulled >= 20  # the weighing prior does move the naming: the test above can tell the two apart


def test_side_cue_settles_the_half_turn():
    """Where the network can tell +z from -z (side right at 80 %), the half-turn is settled without a prior."""
    rng = np.random.default_rng(5)
    counts = collections.Counter()
    for _ in range(40):
        case = make_case(rng, side_acc=0.8)
        naming = name_corners(case["points_px"], case["K"], type_prob=case["type_prob"],
                              image_size=case["image_size"])
        counts[outcome(case, naming)] += 1
    assert counts["right"] >= 36


def test_end_only_cues_are_accepted():
    case = make_case(np.random.default_rng(6), n_spurious=0)
    p = case["type_prob"]
    end_only = np.stack([p[:, 0] + p[:, 1], p[:, 2] + p[:, 3]], -1)
    naming = name_corners(case["points_px"], case["K"], type_prob=end_only, image_size=case["image_size"])
    assert outcome(case, naming) in ("right", "ambiguous") and naming.ambiguous


def test_without_type_cues_all_four_half_turns_are_equally_likely():
    case = make_case(np.random.default_rng(4), n_spurious=0)
    naming = name_corners(case["points_px"], case["K"], image_size=case["image_size"])
    assert abs(naming.probability - 0.25) < 1e-6 and naming.ambiguous


def test_too_few_candidates():
    K = np.array([[1000.0, 0, 500], [0, 1000, 500], [0, 0, 1]])
    assert name_corners(np.array([[1.0, 2.0], [30, 40], [50, 10]]), K) is None


def _edge_prob(case, p_edge=0.9, p_other=0.1):
    """Line-verification probabilities of every candidate pair: box edges high, everything else low."""
    from envisat_pose.geometry import EDGES

    ids = case["truth_id"]
    edges = {tuple(sorted(e)) for e in EDGES}
    m = len(ids)
    prob = np.full((m, m), p_other)
    for i in range(m):
        for j in range(m):
            if ids[i] >= 0 and ids[j] >= 0 and tuple(sorted((ids[i], ids[j]))) in edges:
                prob[i, j] = p_edge
    return prob


def test_line_cues_help_with_many_spurious_junctions():
    """2 px noise, 5 spurious junctions: the line-verification cue keeps the naming right more often (measured on
    the 100 cases, 2026-12-02: 87 % right or flagged without it, 90 % with it; named wrongly 13 and 10 times. On
    60 cases the margin was one case, which a PnP solve's last bits on another CPU can take away)."""
    rates = {}
    for use_lines in (False, True):
        rng = np.random.default_rng(7)
        counts = collections.Counter()
        for _ in range(100):
            case = make_case(rng, noise_px=2.0, n_spurious=5)
            naming = name_corners(case["points_px"], case["K"], type_prob=case["type_prob"],
                                  edge_prob=_edge_prob(case) if use_lines else None, image_size=case["image_size"],
                                  config=NamingConfig(sigma_px=3.0, gate_px=12.0, max_candidates=13))
            counts[outcome(case, naming, tol_px=8.0)] += 1
        rates[use_lines] = (counts["right"] + counts["ambiguous"]) / 100
    print(rates)
    assert rates[True] >= 0.85 and rates[True] > rates[False]


def _with_missed_corners(case, rng, p_miss=0.25):
    """The case with each true corner's candidate dropped with probability p_miss (the network misses some)."""
    keep = (case["truth_id"] < 0) | (rng.random(len(case["truth_id"])) >= p_miss)
    return {**case, **{k: case[k][keep] for k in ("points_px", "truth_id", "type_prob")}}


def test_views_with_missed_corners_are_named():
    """A quarter of the true corners missed (so often no face is found whole), 1 px noise, 3 spurious junctions,
    line cues: faces seen by three corners and a miss cheaper than an unexplained candidate keep the naming
    right far more often than whole faces alone with a miss as costly as an unexplained candidate."""
    rates = {}
    configs = {"whole faces": NamingConfig(max_corner_quads=0, missed_weight=1.0), "default": NamingConfig()}
    for name, cfg in configs.items():
        rng = np.random.default_rng(8)
        counts = collections.Counter()
        n = 0
        while n < 80:
            case = _with_missed_corners(make_case(rng, n_spurious=3), rng)
            if np.sum(case["truth_id"] >= 0) < 4:
                continue
            n += 1
            naming = name_corners(case["points_px"], case["K"], type_prob=case["type_prob"],
                                  edge_prob=_edge_prob(case), image_size=case["image_size"], config=cfg)
            counts[outcome(case, naming, tol_px=6.0, found_only=True)] += 1
        rates[name] = (counts["right"] + counts["ambiguous"]) / n
    print(rates)
    assert rates["default"] >= 0.8 and rates["default"] > rates["whole faces"] + 0.2  # measured 0.86 and 0.51

