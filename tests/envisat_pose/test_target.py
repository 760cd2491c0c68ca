"""The one Target read from an MJCF file: the file in its own terms (angle units, eulerseq), its skeleton and
symmetries against what the geometry plainly has, its exact visibility against MuJoCo's own mj_ray over the whole
file (not the code's per-geom casts), and the default target's corners.

References independent of the code under test: rotations written out by hand in three notations, MuJoCo's mj_ray,
ENVISAT's box edges typed in the core (geometry.EDGES), a box's and a cylinder's symmetries by inspection.
"""

import math
import os

import mujoco
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from envisat_pose.config import ConfigError
from envisat_pose.geometry import EDGES, load_geometry
from envisat_pose.target import load_target

BODY = ('<inertial pos="0 0 0" mass="20" diaginertia="1 2 2.5"/>'
        '<geom name="plate" type="box" size="0.5 0.3 0.05" {plate} rgba="0.7 0.7 0.7 1"/>'
        '<geom name="rod" type="cylinder" fromto="0 0 0.05 0 0 0.6" size="0.05" rgba="0.2 0.2 0.8 1"/>'
        '{sites}')
# the plate is written turned 90 deg about z: its corners at x +-0.3, y +-0.5 (read as 90 rad, 116.6 deg mod 360,
# they would miss the sites by 0.19 m or more and the file be refused)
SITES = {"a": (0.3, 0.5, 0.05), "b": (-0.3, 0.5, 0.05), "c": (-0.3, -0.5, 0.05), "d": (0.3, -0.5, 0.05),
         "top": (0.0, 0.05, 0.6)}


def _file(tmp_path, name, compiler, plate, sites=SITES):
    text = (f'<mujoco model="{name}">{compiler}<worldbody><body name="target">'
            + BODY.format(plate=plate, sites="".join(f'<site name="kp_{k}" pos="{x} {y} {z}"/>'
                                                     for k, (x, y, z) in sites.items()))
            + "</body></worldbody></mujoco>")
    path = tmp_path / f"{name}.xml"
    path.write_text(text)
    return str(path)


def _quat_z(deg):
    h = math.radians(deg) / 2
    return f"{math.cos(h)!r} 0 0 {math.sin(h)!r}"


def _three_notations(tmp_path):
    """The plate turned 90 deg about z as MuJoCo teaches (euler in degrees, the default unit), in radians under
    <compiler angle="radian">, and as a quaternion."""
    return [_file(tmp_path, "deg", "", 'euler="0 0 90"'),
            _file(tmp_path, "rad", '<compiler angle="radian"/>', f'euler="0 0 {math.radians(90)!r}"'),
            _file(tmp_path, "quat", "", f'quat="{_quat_z(90)}"')]


def test_the_file_is_read_in_its_own_angle_unit(tmp_path):
    """Three notations, one shape: the plate's corner where the keypoints say (1e-9 m), the same surfaces,
    reaches and skeletons."""
    targets = [load_target(f) for f in _three_notations(tmp_path)]
    ref = targets[0]
    v = ref.mesh().vertices_T_m
    assert np.min(np.linalg.norm(v - np.array(SITES["a"]), axis=1)) < 1e-9, "the plate is turned 90 deg"
    for t in targets[1:]:
        np.testing.assert_allclose(t.keypoints_T_m, ref.keypoints_T_m, atol=1e-12)
        np.testing.assert_allclose(t.mesh().vertices_T_m, v, atol=1e-9)
        assert abs(t.reach_m - ref.reach_m) < 1e-9 and t.skeleton == ref.skeleton


def test_the_factory_renders_the_shape_mujoco_gives_the_file(tmp_path):
    """The three notations rendered in the factory's scene (256 px, one view): masks equal on all but 0.1 % of the
    pixels (the rasterizer at an edge), keypoint labels within 1e-9 px, and the plate really turned (its mask
    spans the view's projection of the corners)."""
    from envisat_pose.datagen.labels import make_label
    from envisat_pose.datagen.render import SceneRenderer
    from envisat_pose.datagen.render_view import View

    view = View(np.array([0.1, 3.0, -0.05]), np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]]),
                np.array([0.0, -1.0, 0.0]))
    masks, points = [], []
    for f in _three_notations(tmp_path):
        t = load_target(f)
        r = SceneRenderer(256, target=f)
        try:
            out = r.render(view)
            label = make_label(out.corners_K_m, t.visible(out.R_K_from_T, out.t_K_from_T_m), r.K, out.R_K_from_T,
                               out.t_K_from_T_m, np.zeros(12), 0.002, {}, 0, {}, t.keypoint_names)
        finally:
            r.close()
        masks.append(out.mask_u8 > 0)
        points.append(np.array(label["keypoints_px"]))
    for m, p in zip(masks[1:], points[1:]):
        assert np.mean(m != masks[0]) <= 1e-3
        np.testing.assert_allclose(p, points[0], atol=1e-9)
    corners = points[0][:4]
    span = np.ptp(np.argwhere(masks[0])[:, ::-1], axis=0)
    assert np.all(span >= 0.9 * np.ptp(corners, axis=0)), (span, np.ptp(corners, axis=0))


def test_the_default_target_is_envisat_with_corners_a_to_h():
    t = load_target()
    g = load_geometry()
    assert t.keypoint_names == tuple("ABCDEFGH") and t.own_scene and t.name == "envisat"
    np.testing.assert_array_equal(t.keypoints_T_m, g.corners_T_m)
    assert not t.labels_name_keypoints
    assert abs(t.mass_kg - 7827.867) < 1e-9 and abs(t.inertia_T_kg_m2[0, 2] + 2171.4) < 1e-6


def test_envisats_skeleton_is_its_box_edges_and_its_half_turn_is_broken_by_the_materials():
    t = load_target()
    assert list(t.skeleton) == sorted(tuple(sorted(e)) for e in EDGES)
    by_axis = {tuple(np.round(s.axis_T, 6)): s for s in t.symmetries}
    x = by_axis[(1.0, 0.0, 0.0)]
    assert abs(x.angle_deg - 180.0) < 1e-6 and x.broken_by == "materials"
    assert [t.keypoint_names[k] for k in x.perm] == list("CDABGHEF")
    # the half-turns about y and z move the solar array to the other end
    assert {s.broken_by for s in t.symmetries if s is not x} == {"shape"}


def test_a_plain_box_has_its_half_turns_and_a_square_one_its_quarter_turns(tmp_path):
    corners = {f"k{i}": (sx * 0.4, sy * 0.3, sz * 0.2) for i, (sx, sy, sz) in
               enumerate((sx, sy, sz) for sx in (1, -1) for sy in (1, -1) for sz in (1, -1))}
    text = ('<mujoco><worldbody><body name="target"><inertial pos="0 0 0" mass="5" diaginertia="1 1.2 1.4"/>'
            '<geom type="box" size="{} {} {}" rgba="0.5 0.5 0.5 1"/>{}</body></worldbody></mujoco>')
    sites = "".join(f'<site name="kp_{k}" pos="{x} {y} {z}"/>' for k, (x, y, z) in corners.items())
    path = tmp_path / "box.xml"
    path.write_text(text.format(0.4, 0.3, 0.2, sites))
    box = load_target(str(path))
    assert len(box.skeleton) == 12 and len(box.symmetries) == 3
    assert all(abs(s.angle_deg - 180) < 1e-6 and s.broken_by == "" for s in box.symmetries)
    square = {k: (x, y * 0.4 / 0.3, z) for k, (x, y, z) in corners.items()}  # 0.4 x 0.4 cross-section about z
    sites = "".join(f'<site name="kp_{k}" pos="{x} {y} {z}"/>' for k, (x, y, z) in square.items())
    path.write_text(text.format(0.4, 0.4, 0.2, sites))
    sq = load_target(str(path))
    angles = sorted(round(s.angle_deg) for s in sq.symmetries)
    assert angles == [90, 180, 180, 180, 180, 180, 270], angles  # 4-fold about z, 2-fold about x, y, diagonals
    # each symmetry's axis and angle are its rotation (the quarter-turn the other way read 90 deg about +z too)
    for s in sq.symmetries + box.symmetries:
        np.testing.assert_allclose(Rotation.from_rotvec(np.radians(s.angle_deg) * s.axis_T).as_matrix(), s.R_T,
                                   atol=1e-6)


def test_a_rims_skeleton_follows_the_rim(tmp_path):
    """Four points on a cylinder's rim are joined to their neighbours along the rim, not across it; a point alone
    on the other rim (its path comes back to itself) is joined to its nearest keypoint, straight up the side."""
    rim = {f"r{i}": (0.3 * math.cos(a), 0.3 * math.sin(a), 0.5) for i, a in
           enumerate(np.radians([0, 90, 180, 270]))}
    rim["base"] = (0.3, 0.0, -0.5)
    sites = "".join(f'<site name="kp_{k}" pos="{x!r} {y!r} {z}"/>' for k, (x, y, z) in rim.items())
    path = tmp_path / "can.xml"
    path.write_text('<mujoco><worldbody><body name="target"><inertial pos="0 0 0" mass="5" '
                    'diaginertia="1 1 0.5"/><geom type="cylinder" size="0.3 0.5"/>' + sites
                    + '</body></worldbody></mujoco>')
    can = load_target(str(path))
    assert can.skeleton == ((0, 1), (0, 3), (0, 4), (1, 2), (2, 3))


def test_visibility_is_mujocos_ray_cast(tmp_path):
    """Exact visibility from 300 random camera positions 1.5-4 m away: the same answer as mj_ray over the whole
    file for every keypoint (rim points at silhouettes, the rod's top behind the plate seen from below)."""
    path = _file(tmp_path, "vis", "", 'euler="0 0 90"')
    t = load_target(path)
    model = mujoco.MjModel.from_xml_path(path)
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    rng = np.random.default_rng(5)
    geomid = np.zeros(1, np.int32)
    agree = total = hidden = 0
    for _ in range(300):
        d = rng.standard_normal(3)
        cam = d / np.linalg.norm(d) * rng.uniform(1.5, 4.0)
        mine = t.visible_from(cam)
        for k, p in enumerate(t.keypoints_T_m):
            dist = np.linalg.norm(p - cam)
            hit = mujoco.mj_ray(model, data, cam, (p - cam) / dist, None, 1, -1, geomid)
            ray = hit < 0 or hit >= dist - 1e-3
            agree += int(ray == mine[k])
            hidden += int(not ray)
            total += 1
    assert hidden > 300 and agree / total >= 0.999, (agree, total, hidden)


def test_a_keypoint_behind_the_camera_is_not_visible(tmp_path):
    """The camera 3 m out along +x, looking along +x (away from the target): every keypoint has a clear line to
    the camera's centre from the outer side, so visible_from says so for some, yet each lies behind the image
    plane (z_K = R v + t < 0, computed here) and `visible` says none is seen; turned to face the target, the
    camera sees what visible_from says."""
    t = load_target(_file(tmp_path, "behind", "", 'euler="0 0 90"'))
    c_T = np.array([3.0, 0.0, 0.0])
    # K: x right, y down, z the boresight; looking along +x of T: z_K = +x_T, x_K = -y_T, y_K = -z_T
    R_away = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])
    R_facing = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, -1.0], [-1.0, 0.0, 0.0]])
    clear = t.visible_from(c_T)
    assert clear.any()
    for R, in_front in ((R_away, False), (R_facing, True)):
        tvec = -R @ c_T
        z_K = t.keypoints_T_m @ R[2] + tvec[2]
        assert (z_K > 0).all() == in_front and (z_K < 0).all() == (not in_front)
        assert t.visible(R, tvec).tolist() == (clear & in_front).tolist()


def _massed_box(tmp_path, name, extra=""):
    """A file without <inertial>: a 100 kg box (half-sizes 0.5, 0.4, 0.3 m) with a 5 kg ball (r 0.1 m) at x = +-0.6
    m, extra geoms after them."""
    corners = "".join(f'<site name="kp_{i}" pos="{sx * 0.5} {sy * 0.4} {sz * 0.3}"/>' for i, (sx, sy, sz) in
                      enumerate([(1, 1, 1), (-1, 1, 1), (1, -1, 1), (1, 1, -1), (-1, -1, -1)]))
    path = tmp_path / f"{name}.xml"
    path.write_text('<mujoco><worldbody><body name="target"><geom type="box" size="0.5 0.4 0.3" mass="100"/>'
                    '<geom type="sphere" pos="0.6 0 0" size="0.1" mass="5"/>'
                    f'<geom type="sphere" pos="-0.6 0 0" size="0.1" mass="5"/>{extra}{corners}'
                    '</body></worldbody></mujoco>')
    return str(path)


def test_a_file_without_an_inertial_takes_mujocos_inertia_from_its_geoms(tmp_path):
    """As MjModel.from_xml_path reads the file: mass and inertia from the geoms' masses, here by hand (a solid box
    m/3 (b^2 + c^2) on its half-sizes, a ball 2/5 m r^2 moved by m d^2), to 1e-9 relative; the factory's scene
    holds the same inertia; a geom that moves the CoM off the origin is refused, naming where MuJoCo puts it."""
    from envisat_pose.datagen.target_scene import scene_xml

    t = load_target(_massed_box(tmp_path, "massed"))
    ball = 0.4 * 5 * 0.1 ** 2
    expected = np.diag([100 / 3 * (0.4 ** 2 + 0.3 ** 2) + 2 * ball,
                        100 / 3 * (0.5 ** 2 + 0.3 ** 2) + 2 * (ball + 5 * 0.6 ** 2),
                        100 / 3 * (0.5 ** 2 + 0.4 ** 2) + 2 * (ball + 5 * 0.6 ** 2)])
    assert abs(t.mass_kg - 110.0) < 1e-9
    np.testing.assert_allclose(t.inertia_T_kg_m2, expected, rtol=1e-9, atol=1e-9)
    scene = mujoco.MjModel.from_xml_string(scene_xml(t))
    b = scene.body("target").id
    q = scene.body_iquat[b]
    R = np.zeros(9)
    mujoco.mju_quat2Mat(R, q)
    R = R.reshape(3, 3)
    np.testing.assert_allclose(R @ np.diag(scene.body_inertia[b]) @ R.T, expected, rtol=1e-9, atol=1e-9)
    assert abs(scene.body_mass[b] - 110.0) < 1e-9
    with pytest.raises(ConfigError, match=r"MuJoCo puts it at \[0\.0258620"):  # 6 kg more at x = 0.5: 3 / 116 m
        load_target(_massed_box(tmp_path, "off", '<geom type="sphere" pos="0.5 0 0" size="0.05" mass="6"/>'))
    # a feather (1e-5 kg at 0.5 m: the CoM 4.3e-8 m off on a 1.3 m body) or positions rounded to 7 decimals are
    # what users write: within COM_TOLERANCE of the model's size, taken (it was refused beyond 1e-9 m)
    feather = load_target(_massed_box(tmp_path, "feather", '<geom type="sphere" pos="0.5 0 0" size="0.05" '
                                                           'mass="1e-5"/>'))
    assert abs(feather.mass_kg - 110.00001) < 1e-9


def test_a_keypoint_off_the_surface_and_a_file_without_one_are_refused(tmp_path):
    far = dict(SITES, far=(0.0, 0.0, 1.0))
    with pytest.raises(ConfigError, match="site 'kp_far' is 0.400 m from the nearest surface of the geoms"):
        load_target(_file(tmp_path, "far", "", 'euler="0 0 90"', sites=far))
    with pytest.raises(ConfigError, match="at least 4 keypoint sites"):
        load_target(_file(tmp_path, "few", "", 'euler="0 0 90"', sites=dict(list(SITES.items())[:3])))
    with pytest.raises(ConfigError, match="site 'kp_a' is 0.19"):  # 90 read as radians: the corners miss
        load_target(_file(tmp_path, "radians", '<compiler angle="radian"/>', 'euler="0 0 90"'))


@pytest.mark.parametrize("name", ["cubesat_3u", "upper_stage"])
@pytest.mark.parametrize("span", [(2.0, 8.0), (8.0, 150.0)])
def test_the_fast_visibility_table_calls_hidden_only_what_is_hidden(name, span):
    """The table over 2,048 view directions and four ranges against the exact ray casts from 150 random positions,
    range log-uniform over the span in reaches (seed 3): at most 1 % of the visible keypoints called hidden (what
    the filter's check would drop; measured over 400: 0.1-0.4 %), at most 15 % of the hidden ones called visible
    (measured 9-11 %)."""
    t = load_target(f"models/{name}.xml")
    table = t.visibility_table()
    rng = np.random.default_rng(3)
    dropped = visible = passed = hidden = 0
    for _ in range(150):
        d = rng.standard_normal(3)
        c = d / np.linalg.norm(d) * np.exp(rng.uniform(*np.log(span))) * t.reach_m
        exact, fast = t.visible_from(c), table.lookup(c)
        dropped += int(np.sum(exact & ~fast))
        visible += int(exact.sum())
        passed += int(np.sum(~exact & fast))
        hidden += int((~exact).sum())
    assert dropped / visible <= 0.01, (dropped, visible)
    assert passed / hidden <= 0.15, (passed, hidden)
    assert table.visible.any(axis=(0, 1)).all(), "every keypoint is seen from some direction"
    np.testing.assert_array_equal(table.lookup(np.zeros((2, 5, 3)) + [0, 0, 50]).shape, (2, 5, t.num_keypoints))


def _reflection_onto(X, Y):
    """The orthogonal S (reflections allowed) that best maps the rows of X onto those of Y (Procrustes)."""
    U, _, Vt = np.linalg.svd(Y.T @ X)
    return U @ Vt


@pytest.mark.parametrize("name, mirrored", [("models/cubesat_3u.xml", True), ("models/envisat.xml", False),
                                            ("models/upper_stage.xml", False)])
def test_a_mirror_symmetry_relabels_a_flipped_image(name, mirrored):
    """The CubeSat has mirror planes its materials keep; ENVISAT's box has mirrors its materials (and array)
    break, the upper stage none. Where a mirror exists, a left-right flipped image (u -> W - u, a camera centred
    at W / 2) with keypoint j taking flipped keypoint perm[j] (Ultralytics's flip_idx) is the image of the target
    at the proper pose F R S, F t (F the camera's x mirror, S the reflection found here by Procrustes from the
    keypoints alone), to 1e-9 px."""
    t = load_target(name)
    perm = t.mirror_perm
    assert (perm is not None) == mirrored
    if perm is None:
        return
    X = t.keypoints_T_m
    S = _reflection_onto(X, X[list(perm)])
    assert np.linalg.det(S) < 0 and np.allclose(S @ S, np.eye(3), atol=1e-9)
    np.testing.assert_allclose(X @ S.T, X[list(perm)], atol=1e-9)
    W, f = 1024.0, 900.0
    K = np.array([[f, 0, W / 2], [0, f, W / 2], [0, 0, 1]])
    F = np.diag([-1.0, 1.0, 1.0])
    rng = np.random.default_rng(7)
    for R in Rotation.random(5, random_state=rng).as_matrix():  # scipy's, not the project's attitude module
        tvec = np.array([rng.uniform(-0.2, 0.2), rng.uniform(-0.2, 0.2), 3.0])

        def project(R_, t_):
            p = (X @ R_.T + t_) @ K.T
            return p[:, :2] / p[:, 2:]

        uv = project(R, tvec)
        flipped = np.c_[W - uv[:, 0], uv[:, 1]][list(perm)]  # Ultralytics: new keypoint j <- old flip_idx[j]
        R_m = F @ R @ S
        assert np.linalg.det(R_m) > 0
        np.testing.assert_allclose(flipped, project(R_m, F @ tvec), atol=1e-9)


def test_keypoints_no_edge_joins_are_joined_to_their_nearest(tmp_path):
    """Keypoints in the middle of a panel's four edges (each path turns 90 deg at the panel's corners) and one on a
    ball (no sharp edge): each joined to its nearest keypoint, not left out of the skeleton (COCO's, the plots')."""
    mids = {"px": (0.5, 0.0, 0.05), "py": (0.0, 0.3, 0.05), "mx": (-0.5, 0.0, 0.05), "my": (0.0, -0.3, 0.05),
            "ball": (0.0, 0.0, 0.45)}
    sites = "".join(f'<site name="kp_{k}" pos="{x} {y} {z}"/>' for k, (x, y, z) in mids.items())
    path = tmp_path / "panel.xml"
    path.write_text('<mujoco><worldbody><body name="target"><inertial pos="0 0 0" mass="5" '
                    'diaginertia="1 1 0.5"/><geom type="box" size="0.5 0.3 0.05"/>'
                    '<geom type="sphere" size="0.15" pos="0 0 0.3"/>' + sites + '</body></worldbody></mujoco>')
    panel = load_target(str(path))
    # nearest of each: px (0) -> py (1) and my (3) tie at 0.583 m, the lower index; py (1) -> ball (4) at 0.50 m
    # against px at 0.583; mx (2) -> py; my (3) -> ball; ball (4) -> py (0.50, before my at 0.50 by index)
    assert panel.skeleton == ((0, 1), (1, 2), (1, 4), (3, 4)), panel.skeleton


@pytest.mark.parametrize("inertial", ['fullinertia="10 20 30 0 0 0"',  # a lamina: A + B = C exactly
                                      'diaginertia="10 20 30" quat="0.9238795325112867 0 0 0.3826834323650898"',
                                      'fullinertia="15 15 30 5 0 0"'])  # the same plate turned 45 deg about z
def test_a_plates_inertia_goes_into_the_scene_as_mujoco_reads_the_file(tmp_path, inertial):
    """A + B = C holds with equality for a flat plate. The scene once held the tensor rebuilt from MuJoCo's
    principal moments, whose round-off (8.9e-15 off the diagonal) failed MuJoCo's A + B >= C: `simulate` ended in
    a traceback on a file MjModel.from_xml_path compiles. The scene's inertia equals the file's to 1e-12."""
    from envisat_pose.datagen.target_scene import scene_xml

    path = tmp_path / "plate.xml"
    path.write_text(f'<mujoco><worldbody><body name="target"><inertial pos="0 0 0" mass="50" {inertial}/>'
                    '<geom type="box" size="1 0.6 0.02"/>'
                    + "".join(f'<site name="kp_{i}" pos="{sx} {sy * 0.6} 0.02"/>'
                              for i, (sx, sy) in enumerate([(1, 1), (-1, 1), (-1, -1), (1, -1)]))
                    + "</body></worldbody></mujoco>")
    alone = mujoco.MjModel.from_xml_path(str(path))  # what the user checked
    b = alone.body("target").id
    R = np.zeros(9)
    mujoco.mju_quat2Mat(R, alone.body_iquat[b])
    J = R.reshape(3, 3) @ np.diag(alone.body_inertia[b]) @ R.reshape(3, 3).T
    t = load_target(str(path))
    np.testing.assert_allclose(t.inertia_T_kg_m2, J, rtol=0, atol=1e-12)
    scene = mujoco.MjModel.from_xml_string(scene_xml(t))
    s = scene.body("target").id
    mujoco.mju_quat2Mat(R, scene.body_iquat[s])
    np.testing.assert_allclose(R.reshape(3, 3) @ np.diag(scene.body_inertia[s]) @ R.reshape(3, 3).T, J, rtol=0,
                               atol=1e-12)


@pytest.mark.parametrize("name", ["sat.mjcf", "SAT.XML", "sat"])
def test_a_target_file_not_named_xml_is_refused_for_its_name(tmp_path, capfd, name):
    """MuJoCo reads a model file by its name's ending, and .xml alone as MJCF: a good MJCF file named sat.mjcf (or
    SAT.XML, or with no ending) was refused as 'an MJCF file MuJoCo reads (it says: could not find decoder for
    resource ...)', with MuJoCo's two WARNING lines before it where the name has no ending."""
    import shutil

    models = os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))), "models")
    path = tmp_path / name
    shutil.copy(os.path.join(models, "cubesat_3u.xml"), path)
    capfd.readouterr()
    with pytest.raises(ConfigError, match=r"expected an MJCF file whose name ends in \.xml") as err:
        load_target(str(path))
    assert err.value.field == "target" and err.value.value == str(path)
    assert capfd.readouterr() == ("", "")
    shutil.copy(path, tmp_path / "sat.xml")
    assert load_target(str(tmp_path / "sat.xml")).keypoint_names  # the same file named .xml is read
