"""Labels match pixels: corners recovered from the rendered mask and depth lie within 1 px of the projected
labels; rendered depth matches the face planes of the labelled pose; the depth test sees the solar array."""

import os

os.environ.setdefault("MUJOCO_GL", "osmesa")

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation


def cross2(a, b):
    """z of the cross product of 2D vectors (..., 2)."""
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]

from envisat_pose.attitude import quat_to_rotmat
from envisat_pose.datagen.labels import make_label
from envisat_pose.datagen.render import SceneRenderer
from envisat_pose.datagen.render_view import MASK_VALUES, View
from envisat_pose.geometry import load_geometry, visible_corners
from envisat_pose.target import load_target

RES = 256


@pytest.fixture(scope="module")
def renderer():
    r = SceneRenderer(RES)
    yield r
    r.close()


def random_views(n, seed):
    """Views at 24-40 m near the boresight, random attitude and sun (an independent sampler from the factory's)."""
    rng = np.random.default_rng(seed)
    views = []
    for _ in range(n):
        q = rng.standard_normal(4)
        rng_m = rng.uniform(24.0, 40.0)
        off = rng.uniform(-0.1, 0.1, size=2)
        rho = rng_m * np.array([off[1], 1.0, off[0]]) / np.linalg.norm([off[1], 1.0, off[0]])
        sun = rng.standard_normal(3)
        views.append(View(rho, quat_to_rotmat(q / np.linalg.norm(q)), sun))
    return views


def edge_points(region):
    """Mid-points between each inside pixel and its outside 4-neighbour: within 0.5 px of the true edge. (P, 2)."""
    r = region.astype(bool)
    ys, xs = np.nonzero(r[:, 1:] != r[:, :-1])
    pts = [np.stack([xs + 0.5, ys], 1)]
    ys, xs = np.nonzero(r[1:, :] != r[:-1, :])
    pts.append(np.stack([xs, ys + 0.5], 1))
    return np.concatenate(pts).astype(float)


def polygon_vertices(region):
    """Sub-pixel vertices of a region's outline: a rough polygon, a line fitted to each of its sides, and the
    intersections of neighbouring sides. (V, 2) px, OpenCV convention, and (V,) bool: refined (both sides
    fitted) rather than a rough polygon vertex."""
    contours, _ = cv2.findContours(region.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    if not contours:
        return np.zeros((0, 2)), np.zeros(0, bool)
    contour = max(contours, key=cv2.contourArea)
    if cv2.contourArea(contour) < 30:
        return np.zeros((0, 2)), np.zeros(0, bool)
    rough = cv2.approxPolyDP(contour, 2.5, True)[:, 0, :].astype(float)
    pts = edge_points(region)
    lines = []
    for a, b in zip(rough, np.roll(rough, -1, axis=0)):
        ab = b - a
        length = np.linalg.norm(ab)
        if length < 8:
            lines.append(None)
            continue
        t = (pts - a) @ ab / length**2
        dist = np.abs(cross2(ab, pts - a)) / length
        sel = pts[(dist < 3.0) & (t > 3 / length) & (t < 1 - 3 / length)]
        if len(sel) < 5:
            lines.append(None)
            continue
        for _ in range(3):  # refit on the points near the current line
            c = sel.mean(0)
            _, _, vt = np.linalg.svd(sel - c)
            near = pts[(np.abs(cross2(vt[0], pts - c)) < 0.8) & (np.abs((pts - c) @ vt[0]) < 0.5 * length - 2)]
            if len(near) < 5:
                break
            sel = near
        lines.append((c, vt[0]))
    verts, refined = [], []
    for k in range(len(rough)):
        l1, l2 = lines[k - 1], lines[k]
        if l1 is None or l2 is None or abs(cross2(l1[1], l2[1])) < 0.2:
            verts.append(rough[k])
            refined.append(False)
            continue
        # c1 + s d1 = c2 + r d2
        A = np.stack([l1[1], -l2[1]], 1)
        s, _ = np.linalg.solve(A, l2[0] - l1[0])
        verts.append(l1[0] + s * l1[1])
        refined.append(True)
    return np.array(verts), np.array(refined)


def clear_corners(out):
    """Corners none of whose faces is seen at a grazing angle (|cos| < 0.15): a face seen edge-on is a sliver
    thinner than a pixel, which rasterization drops, so its corners have no pixel evidence. (8,) bool."""
    g = load_geometry()
    clear = np.ones(8, dtype=bool)
    for k in range(6):
        n_K = out.R_K_from_T @ g.face_normals_T[k]
        centre_K = out.t_K_from_T_m + out.R_K_from_T @ (g.face_normals_T[k] * g.face_offsets_m[k])
        cos = -n_K @ centre_K / np.linalg.norm(centre_K)
        if abs(cos) < 0.15:
            clear &= ~g.face_corners[k]
    return clear


def test_corners_from_mask_within_one_pixel(renderer):
    checked, reverse_checked = 0, 0
    for view in random_views(16, seed=7):
        out = renderer.render(view)
        lab = _label(out, renderer)
        corners = np.array(lab["corners_px"])
        body = (out.mask_u8 >= 1) & (out.mask_u8 <= 6)
        regions = [out.mask_u8 == v for v in range(1, 7)] + [body]
        verts = np.concatenate([polygon_vertices(r)[0] for r in regions])
        array_near = cv2.dilate((out.mask_u8 == MASK_VALUES["array"]).astype(np.uint8), np.ones((9, 9), np.uint8))
        clear = clear_corners(out)
        for i in range(8):
            u, v = corners[i]
            if not (lab["visible"][i] and clear[i] and 4 <= u <= RES - 5 and 4 <= v <= RES - 5):
                continue
            if array_near[int(round(v)), int(round(u))]:
                continue
            d = np.min(np.linalg.norm(verts - corners[i], axis=1))
            assert d < 1.0, f"corner {'ABCDEFGH'[i]} at {corners[i]} has no rendered vertex within 1 px ({d:.2f})"
            # the depth next to the corner is the corner's own depth
            z = out.corners_K_m[i, 2]
            win = out.depth_m[int(round(v)) - 1 : int(round(v)) + 2, int(round(u)) - 1 : int(round(u)) + 2]
            assert np.min(np.abs(win[win > 0] - z)) < 3 * z / renderer.K[0, 0]  # within ~1.5 px footprints
            checked += 1
        # reverse: vertices of the body silhouette away from the array and the border are labelled corners
        boom_near = cv2.dilate(array_near, np.ones((9, 9), np.uint8))  # fitted sides extend past the boom
        silhouette, refined = polygon_vertices(body)
        for p in silhouette[refined]:
            if np.any(p < 4) or np.any(p > RES - 5) or boom_near[int(round(p[1])), int(round(p[0]))]:
                continue
            if np.any(np.linalg.norm(corners[~clear] - p, axis=1) < 5):
                continue
            assert np.min(np.linalg.norm(corners - p, axis=1)) < 1.0, f"silhouette vertex {p} is no labelled corner"
            reverse_checked += 1
    assert checked >= 40 and reverse_checked >= 30, (checked, reverse_checked)


# Independent target geometry for ray casting, from the reference sheet (sections 1 and 5) and the MJCF's
# stated sizes: the main body box, the solar array plate and the boom's bounding box, in T.
BODY_HALF_M = np.array([5.0, 1.375, 1.0375])
ARRAY_CENTRE_M, ARRAY_HALF_M = np.array([-15.0, 0.0, 0.0]), np.array([7.0, 2.5, 0.02])
BOOM_CENTRE_M, BOOM_HALF_M = np.array([-6.5, 0.0, 0.0]), np.array([1.5, 0.08, 0.08])


def ray_box(o, d, centre, half):
    """Slab test of rays o + s d (o (3,), d (N, 3)) against an axis-aligned box: entry s (inf on a miss) and
    the entry axis and side (+1: the ray enters through the box's + face). (N,), (N,), (N,)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t0 = (centre - half - o) / d
        t1 = (centre + half - o) / d
    near, far = np.minimum(t0, t1), np.maximum(t0, t1)
    s_in, s_out = near.max(axis=1), far.min(axis=1)
    axis = near.argmax(axis=1)
    side = -np.sign(d[np.arange(len(d)), axis])
    hit = (s_in <= s_out) & (s_in > 0)
    return np.where(hit, s_in, np.inf), axis, side


def cast(view, uv, K):
    """Depth along the boresight (m, 0 on a miss), mask value (the contract's) and whether the ray touches the
    boom's box, of pixel rays uv (N, 2) for the view's pose: independent of the renderer."""
    R_K_from_C = np.array([[0.0, 0.0, -1.0], [-1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    R_K_T = R_K_from_C @ view.R_C_from_T
    t_K = R_K_from_C @ view.rho_C_m
    d_K = np.column_stack([uv, np.ones(len(uv))]) @ np.linalg.inv(K).T  # z = 1: s is the depth
    o_T, d_T = -R_K_T.T @ t_K, d_K @ R_K_T
    s_body, axis, side = ray_box(o_T, d_T, np.zeros(3), BODY_HALF_M)
    s_array = ray_box(o_T, d_T, ARRAY_CENTRE_M, ARRAY_HALF_M)[0]
    s_boom = ray_box(o_T, d_T, BOOM_CENTRE_M, BOOM_HALF_M * 1.5)[0]
    face_value = 1 + 2 * axis + (side < 0)  # px 1, mx 2, py 3, my 4, pz 5, mz 6
    s = np.minimum(s_body, s_array)
    mask = np.where(s_body <= s_array, face_value, MASK_VALUES["array"])
    mask = np.where(np.isinf(s), 0, mask)
    return np.where(np.isinf(s), 0.0, s), mask, np.isfinite(s_boom)


def test_depth_and_mask_match_independent_ray_casting(renderer):
    """Every pixel's rendered depth and mask value against a ray cast from the view's pose through the box
    geometry written out above. Pixels within 0.75 px of an edge (neighbouring rays disagree on what they
    hit) and rays touching the boom (a cylinder here only boxed) are left out."""
    ys, xs = np.mgrid[0:RES, 0:RES]
    uv = np.column_stack([xs.ravel(), ys.ravel()]).astype(float)
    n_face_px = np.zeros(8, dtype=int)
    for view in random_views(6, seed=3):
        out = renderer.render(view)
        depth, mask, boom = cast(view, uv, renderer.K)
        agree = np.ones(len(uv), dtype=bool)
        for du, dv in ((0.75, 0), (-0.75, 0), (0, 0.75), (0, -0.75)):
            _, m2, b2 = cast(view, uv + [du, dv], renderer.K)
            agree &= (m2 == mask) & ~b2
        keep = agree & ~boom
        rendered_mask = out.mask_u8.ravel()[keep]
        assert np.mean(rendered_mask == mask[keep]) > 0.999, np.mean(rendered_mask == mask[keep])
        fg = keep & (mask > 0)
        err = np.abs(out.depth_m.ravel()[fg] - depth[fg])
        assert err.max() < 0.01, err.max()
        assert np.all(out.depth_m.ravel()[keep & (mask == 0)] == 0)
        n_face_px += np.bincount(mask[fg], minlength=8)
    assert np.count_nonzero(n_face_px[1:7] > 200) >= 5 and n_face_px[7] > 200, n_face_px  # faces and array seen


def test_pose_in_camera_frame_matches_state(renderer):
    """K axes on the chaser: x_K = -z_C, y_K = -x_C (image up is radial out), z_K = +y_C (boresight)."""
    view = random_views(1, seed=5)[0]
    out = renderer.render(view)
    R_K_from_C = np.array([[0.0, 0.0, -1.0], [-1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    np.testing.assert_allclose(out.t_K_from_T_m, R_K_from_C @ view.rho_C_m, atol=1e-9)
    np.testing.assert_allclose(out.R_K_from_T, R_K_from_C @ view.R_C_from_T, atol=1e-9)
    corners_K = out.t_K_from_T_m + load_geometry().corners_T_m @ out.R_K_from_T.T
    np.testing.assert_allclose(out.corners_K_m, corners_K, atol=1e-9)


def test_the_lit_pass_alone_gives_the_same_image_and_pose(renderer):
    """render(view, labels=False) (the closed loop's) skips the depth and mask pass only: the same pixels and
    pose as with labels, whichever came before."""
    views = random_views(3, seed=11)
    full = [renderer.render(v) for v in views]
    lit = [renderer.render(v, labels=False) for v in views[::-1]][::-1]
    for a, b in zip(full, lit):
        assert b.depth_m is None and b.mask_u8 is None
        assert a.gray_u8.tobytes() == b.gray_u8.tobytes() and a.gray_u8.any()
        np.testing.assert_array_equal(a.R_K_from_T, b.R_K_from_T)
        np.testing.assert_array_equal(a.t_K_from_T_m, b.t_K_from_T_m)


def _label(out, renderer, appendages=False) -> dict:
    """The factory's label of a render: visibility from the Target's ray casts."""
    unoccluded = load_target().visible(out.R_K_from_T, out.t_K_from_T_m, appendages)
    return make_label(out.corners_K_m, unoccluded, renderer.K, out.R_K_from_T, out.t_K_from_T_m, np.zeros(12),
                      0.002, {}, 0, {})


def test_ray_cast_visibility_agrees_with_face_test_and_sees_the_array(renderer):
    agree = total = 0
    for view in random_views(10, seed=11):
        out = renderer.render(view)
        lab = _label(out, renderer)
        c_T = -view.R_C_from_T.T @ view.rho_C_m
        exact = visible_corners(c_T)
        visible = np.array(lab["visible"])
        assert not np.any(visible & ~exact), "a corner behind the box was labelled visible"
        for i in np.flatnonzero(lab["in_frame"]):
            total += 1
            if visible[i] == exact[i]:
                agree += 1
                continue
            # a face-visible corner labelled hidden must have the array (or boom) in front of it
            u, v = np.rint(lab["corners_px"][i]).astype(int)
            agree += bool(out.mask_u8[v, u] == MASK_VALUES["array"] and out.depth_m[v, u] < out.corners_K_m[i, 2] - 0.25)
    assert total >= 70 and agree / total > 0.97, (agree, total)
    # seen from the -x end, a little from below (-z): the array (z = 0 plane, x in [-22, -8]) lies between the
    # camera and corners E, F (z = +1.04), which the face test calls visible; G, H (z = -1.04) stay in view
    d_T = np.array([-1.0, 0.0, -0.15]) / np.linalg.norm([-1.0, 0.0, -0.15])  # toward the camera, in T
    R_C_from_T = Rotation.align_vectors([[0.0, -1.0, 0.0]], [d_T])[0].as_matrix()
    view = View(np.array([0.0, 40.0, 0.0]), R_C_from_T, np.array([0.0, -1.0, 0.2]))
    np.testing.assert_allclose(-R_C_from_T.T @ view.rho_C_m, 40.0 * d_T, atol=1e-9)
    out = renderer.render(view)
    lab = _label(out, renderer)
    exact = visible_corners(40.0 * d_T)
    assert exact[[4, 5, 6, 7]].all(), "the face test sees E-H from this side"
    assert lab["visible"][4:] == [False, False, True, True], "the array hides E and F, not G and H"


def test_sun_eclipse_and_earth_backdrop(renderer):
    """Sunlight from behind the camera lights the faces we see; from behind the target it leaves them dark;
    eclipse darkens the target; the Earth backdrop fills background pixels without entering mask or depth."""
    R = quat_to_rotmat(np.array([0.9, 0.3, -0.2, 0.25]) / np.linalg.norm([0.9, 0.3, -0.2, 0.25]))
    rho = np.array([0.0, 35.0, 0.0])
    lit = renderer.render(View(rho, R, np.array([0.1, -1.0, 0.05])))  # sun behind the chaser
    back = renderer.render(View(rho, R, np.array([0.1, 1.0, 0.05])))  # sun behind the target
    dark = renderer.render(View(rho, R, None))  # eclipse
    body = (lit.mask_u8 >= 1) & (lit.mask_u8 <= 6)
    assert body.sum() > 500
    assert np.array_equal(lit.mask_u8, dark.mask_u8) and np.array_equal(lit.depth_m, dark.depth_m)
    m_lit, m_back, m_dark = (o.gray_u8[body].mean() for o in (lit, back, dark))
    assert m_lit > 40 and m_lit > 3 * m_back and m_dark < 8, (m_lit, m_back, m_dark)
    earth = renderer.render(View(rho, R, np.array([0.1, -1.0, 0.05]), earth_dir_C=np.array([0.0, 1.0, -0.3])))
    background = lit.mask_u8 == 0
    assert np.array_equal(earth.mask_u8, lit.mask_u8) and np.array_equal(earth.depth_m, lit.depth_m)
    assert lit.gray_u8[background].mean() < 1 and earth.gray_u8[background].mean() > 20


def test_the_lit_pass_reads_back_only_the_targets_box_with_the_same_pixels(renderer):
    """Where only the target is drawn, the lit pass reads back its box alone and leaves the rest black: byte for
    byte the full frame's read-back of the same render (views near and far, one clipped by the frame's edge, one
    in eclipse); with the Earth in the scene the frame is read whole."""
    import hashlib

    import mujoco

    from envisat_pose.datagen.render_pixels import projected_bbox_px

    R = quat_to_rotmat(np.array([0.9, 0.3, -0.2, 0.25]) / np.linalg.norm([0.9, 0.3, -0.2, 0.25]))
    views = random_views(5, seed=21) + [
        View(np.array([6.0, 30.0, -3.0]), R, np.array([0.1, -1.0, 0.05])),  # off the boresight: clipped
        View(np.array([0.0, 45.0, 0.0]), R, None),  # eclipse
        View(np.array([0.0, 35.0, 0.0]), R, np.array([0.1, -1.0, 0.05]), earth_dir_C=np.array([0.0, 1.0, -0.3]))]
    boxes = []
    for v in views:
        p = renderer.render_passes(v, labels=False)
        full = np.empty((RES, RES, 3), np.uint8)
        mujoco.mjr_readPixels(full, None, renderer._rect, renderer._con)  # the same framebuffer, whole
        assert hashlib.sha256(p.rgb_u8.tobytes()).hexdigest() == hashlib.sha256(full.tobytes()).hexdigest()
        R_K_W, cam_W = renderer.camera_pose()
        boxes.append(projected_bbox_px(renderer._target_hull_K_m(R_K_W, cam_W), renderer.K, RES, renderer.znear_m))
    areas = [(b[2] - b[0] + 1) * (b[3] - b[1] + 1) / RES**2 for b in boxes[:-1] if b is not None]
    assert min(areas) < 0.5, areas  # the box read is a part of the frame, not all of it
    assert p.rgb_u8[:4, :4].any() or p.rgb_u8.mean() > 5  # the Earth's frame was read whole, not left black
