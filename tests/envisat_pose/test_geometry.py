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


def test_camera_equals_mujocos_compiled_camera():
    """The core's pinhole (read from the MJCF text) against MuJoCo's compiled camera chaser_cam: the same
    fovy, resolution and mount, and the same projection of a point."""
    import mujoco

    from envisat_pose.geometry import load_camera, model_path, project_K

    cam = load_camera()
    m = mujoco.MjModel.from_xml_path(model_path())
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)  # chaser mocap at the origin with the identity attitude: world = C
    cid = m.camera("chaser_cam").id
    width, height = m.cam_resolution[cid]
    assert (cam.width_px, cam.height_px) == (width, height)
    np.testing.assert_allclose(cam.f_px, 0.5 * height / np.tan(np.radians(m.cam_fovy[cid]) / 2), rtol=1e-12)
    np.testing.assert_allclose(cam.f_px, 1910.8, atol=0.05)  # reference sheet, section 6
    R_W_mjcam = d.cam_xmat[cid].reshape(3, 3)
    np.testing.assert_allclose(cam.R_K_from_C, (R_W_mjcam * [1.0, -1.0, -1.0]).T, atol=1e-12)
    np.testing.assert_allclose(cam.pos_C_m, d.cam_xpos[cid], atol=1e-12)
    # boresight +y_C: a point 50 m ahead lands on the principal point; one 1 m radially out (image up) above it
    p_K = (np.array([[0.0, 50.0, 0.0], [1.0, 50.0, 0.0]]) - cam.pos_C_m) @ cam.R_K_from_C.T
    uv = project_K(p_K, cam)
    np.testing.assert_allclose(uv[0], [511.5, 511.5], atol=1e-9)
    np.testing.assert_allclose(uv[1], [511.5, 511.5 - cam.f_px / 50.0], atol=1e-9)


def test_projection_never_mirrors_a_point_behind_the_camera():
    from envisat_pose.geometry import load_camera, project_K

    cam = load_camera()
    uv = project_K(np.array([[2.0, -1.0, 10.0], [2.0, -1.0, -10.0], [2.0, -1.0, 0.0]]), cam)
    assert uv[0, 0] > cam.cu_px and uv[0, 1] < cam.cv_px  # in front: right and up
    # behind or on the camera plane: same side as the point's x and y, far outside the image
    assert (uv[1:, 0] > cam.width_px).all() and (uv[1:, 1] < 0).all()
