"""Corners, faces and the exact visibility test, against the reference sheet's tables and a ray test."""

import numpy as np

from envisat_pose.geometry import load_geometry, visible_corners

# shared/reference.md, section 5
SHEET_CORNERS = np.array([
    [5.0, 1.375, 1.0375], [5.0, -1.375, 1.0375], [5.0, -1.375, -1.0375], [5.0, 1.375, -1.0375],
    [-5.0, 1.375, 1.0375], [-5.0, -1.375, 1.0375], [-5.0, -1.375, -1.0375], [-5.0, 1.375, -1.0375],
])
SHEET_FACES = {  # normal: (offset, corners)
    (1, 0, 0): (5.0, "ABCD"), (-1, 0, 0): (5.0, "EFGH"), (0, 1, 0): (1.375, "ADHE"),
    (0, -1, 0): (1.375, "BCGF"), (0, 0, 1): (1.0375, "ABFE"), (0, 0, -1): (1.0375, "CDHG"),
}


def test_corners_and_faces_match_the_sheet():
    g = load_geometry()
    np.testing.assert_array_equal(g.corners_T_m, SHEET_CORNERS)
    for n, h, members in zip(g.face_normals_T, g.face_offsets_m, g.face_corners):
        offset, names = SHEET_FACES[tuple(int(v) for v in n)]
        assert h == offset
        assert set("ABCDEFGH"[i] for i in np.flatnonzero(members)) == set(names)


def _hidden_by_box(c_T, corner, half):
    """Independent ray test: does the segment from the viewpoint to the corner pass through the box interior?"""
    d = corner - c_T
    t0, t1 = 0.0, 1.0 - 1e-7
    for k in range(3):
        lo, hi = -half[k] + 1e-9, half[k] - 1e-9
        if abs(d[k]) < 1e-15:
            if not lo < c_T[k] < hi:
                return False
            continue
        ta, tb = sorted(((lo - c_T[k]) / d[k], (hi - c_T[k]) / d[k]))
        t0, t1 = max(t0, ta), min(t1, tb)
        if t0 >= t1:
            return False
    return True


def test_face_test_equals_ray_casting():
    g = load_geometry()
    rng = np.random.default_rng(11)
    dirs = rng.standard_normal((2000, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    ranges = rng.uniform(6.0, 60.0, size=(2000, 1))
    views = dirs * ranges
    vis = visible_corners(views)
    for c_T, v in zip(views, vis):
        expected = [not _hidden_by_box(c_T, corner, g.half_sizes_m) for corner in g.corners_T_m]
        assert list(v) == expected
    assert set(vis.sum(axis=1)) == {4, 6, 7}


def test_known_viewpoints():
    # straight down the +x axis only the +x face (A B C D) is seen; from the (+,+,+) octant all but G
    np.testing.assert_array_equal(visible_corners(np.array([100.0, 0, 0])), [1, 1, 1, 1, 0, 0, 0, 0])
    np.testing.assert_array_equal(visible_corners(np.array([30.0, 30.0, 30.0])), [1, 1, 1, 1, 1, 1, 0, 1])
    # the paper's u.n < 0 (offset dropped) would call the +x face visible from (2, 40, 0): it is not
    np.testing.assert_array_equal(visible_corners(np.array([2.0, 40.0, 0.0])), [1, 0, 0, 1, 1, 0, 0, 1])
