"""A target written as a tree of bodies (a bus, wings as child bodies, a tip on each wing as a grandchild, one wing
turned half round, a default class, angles in degrees) against the same spacecraft written by hand as one body:
the same keypoints, surface, mass and inertia, the same scene and the same pixels. The composite inertia is
computed here from textbook formulas (solid box m/3 (b^2 + c^2) on half-sizes, solid cylinder, parallel axes),
not by MuJoCo; MuJoCo's own fusestatic does the fusing under test.
"""

import hashlib
import os
import warnings

import mujoco
import numpy as np
import pytest

from envisat_pose.attitude import quat_to_rotmat
from envisat_pose.config import InputError
from envisat_pose.datagen.labels import make_label
from envisat_pose.datagen.render import SceneRenderer
from envisat_pose.datagen.render_view import View
from envisat_pose.datagen.target_scene import scene_xml
from envisat_pose.target import load_target, require_weights_target, resolve_target_path
from envisat_pose.target_assets import target_sha256

TREE = """<mujoco model="treesat">
  <compiler angle="degree"/>
  <default><default class="wing"><geom type="box" size="0.8 0.02 0.3" rgba="0.1 0.1 0.4 1" mass="5"/></default>
  </default>
  <worldbody>
    <body name="target">
      <geom name="bus" type="box" size="0.5 0.5 0.5" mass="200" rgba="0.8 0.7 0.3 1"/>
      <site name="kp_a" pos="0.5 0.5 0.5"/>
      <site name="kp_b" pos="-0.5 0.5 0.5"/>
      <site name="kp_c" pos="0.5 -0.5 -0.5"/>
      <body name="wing_l" pos="1.3 0 0" childclass="wing">
        <geom name="wl"/>
        <site name="kp_wl" pos="0.8 0 0.3"/>
        <body name="tip_l" pos="0.8 0 0" euler="0 90 0">{joint}<geom name="tl" type="cylinder" size="0.05 0.1" mass="1"/>
        </body>
      </body>
      <body name="wing_r" pos="-1.3 0 0" euler="0 0 180" childclass="wing">
        <geom name="wr"/>
        <site name="kp_wr" pos="0.8 0 -0.3"/>
        <body name="tip_r" pos="0.8 0 0" euler="0 90 0"><geom name="tr" type="cylinder" size="0.05 0.1" mass="1"/></body>
      </body>
    </body>
  </worldbody>
</mujoco>"""


def _box_inertia(m, a, b, c):
    return m / 3 * np.array([b * b + c * c, a * a + c * c, a * a + b * b])


def _composite():
    """The tree's inertia about its CoM (the origin, by symmetry), by hand. The tips' axes lie along x."""
    shift = lambda m, d: m * d * d * np.array([0.0, 1.0, 1.0])  # noqa: E731  (a mass moved along x)
    tip_axial, tip_across = 0.5 * 0.05 ** 2, (3 * 0.05 ** 2 + 4 * 0.1 ** 2) / 12
    wing = _box_inertia(5, 0.8, 0.02, 0.3) + shift(5, 1.3)
    tip = np.array([tip_axial, tip_across, tip_across]) + shift(1, 2.1)
    return np.diag(_box_inertia(200, 0.5, 0.5, 0.5) + 2 * wing + 2 * tip)


def _flat(diag):
    """The same spacecraft written by hand as one body: poses composed, the composite inertia stated."""
    wing = 'type="box" size="0.8 0.02 0.3" rgba="0.1 0.1 0.4 1"'
    tip = 'rgba="0.1 0.1 0.4 1"'  # the tips inherit the wings' class
    return f"""<mujoco model="flatsat"><worldbody><body name="target">
      <inertial pos="0 0 0" mass="212" diaginertia="{float(diag[0])!r} {float(diag[1])!r} {float(diag[2])!r}"/>
      <geom name="bus" type="box" size="0.5 0.5 0.5" rgba="0.8 0.7 0.3 1"/>
      <site name="kp_a" pos="0.5 0.5 0.5"/><site name="kp_b" pos="-0.5 0.5 0.5"/><site name="kp_c" pos="0.5 -0.5 -0.5"/>
      <geom name="wl" pos="1.3 0 0" {wing}/>
      <site name="kp_wl" pos="2.1 0 0.3"/>
      <geom name="tl" type="cylinder" size="0.05 0.1" pos="2.1 0 0" quat="0.7071067811865476 0 0.7071067811865476 0"
            {tip}/>
      <geom name="wr" pos="-1.3 0 0" quat="0 0 0 1" {wing}/>
      <site name="kp_wr" pos="-2.1 0 -0.3"/>
      <geom name="tr" type="cylinder" size="0.05 0.1" pos="-2.1 0 0" quat="0 -0.7071067811865476 0 0.7071067811865476"
            {tip}/>
    </body></worldbody></mujoco>"""


@pytest.fixture(scope="module")
def pair(tmp_path_factory):
    folder = tmp_path_factory.mktemp("tree")
    tree, flat = folder / "tree.xml", folder / "flat.xml"
    tree.write_text(TREE.format(joint=""))
    flat.write_text(_flat(np.diag(_composite())))
    return load_target(str(tree)), load_target(str(flat))


def test_a_tree_of_bodies_is_one_rigid_body_with_the_composite_inertia(pair):
    tree, flat = pair
    assert tree.keypoint_names == ("a", "b", "c", "wl", "wr")  # the body's own sites, then its children's
    np.testing.assert_allclose(tree.keypoints_T_m, flat.keypoints_T_m, atol=1e-12)
    assert abs(tree.mass_kg - 212.0) < 1e-9
    np.testing.assert_allclose(tree.inertia_T_kg_m2, _composite(), rtol=1e-12, atol=1e-12)
    assert [g.name for g in tree.geoms] == [g.name for g in flat.geoms]
    assert [g.rgb for g in tree.geoms] == [g.rgb for g in flat.geoms]
    np.testing.assert_allclose(tree.mesh().vertices_T_m, flat.mesh().vertices_T_m, atol=1e-12)
    assert abs(tree.reach_m - flat.reach_m) < 1e-12 and tree.skeleton == flat.skeleton


def test_the_factory_simulates_and_renders_the_tree_as_the_flat_file(pair):
    """The scenes hold the same inertia (the sim's dynamics) and render the same pixels and labels (256 px, one
    view: masks equal on all but 0.1 % of the pixels, the rasterizer's edges; keypoints to 1e-9 px)."""
    inertia = []
    for t in pair:
        m = mujoco.MjModel.from_xml_string(scene_xml(t))
        b = m.body("target").id
        R = quat_to_rotmat(m.body_iquat[b])
        inertia.append(R @ np.diag(m.body_inertia[b]) @ R.T)
        assert m.body_parentid[b] == 0 and np.sum(m.geom_bodyid == b) == 5
    np.testing.assert_allclose(inertia[0], inertia[1], rtol=1e-12, atol=1e-12)
    view = View(np.array([0.2, 9.0, 1.5]), np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]]),
                np.array([0.3, -1.0, 0.2]))
    masks, points = [], []
    for t in pair:
        r = SceneRenderer(256, target=t.path)
        try:
            out = r.render(view)
        finally:
            r.close()
        label = make_label(out.corners_K_m, t.visible(out.R_K_from_T, out.t_K_from_T_m), r.K, out.R_K_from_T,
                           out.t_K_from_T_m, np.zeros(12), 0.002, {}, 0, {}, t.keypoint_names)
        masks.append(out.mask_u8)
        points.append(np.array(label["keypoints_px"]))
    assert np.count_nonzero(masks[0]) > 500
    assert np.mean(masks[0] != masks[1]) <= 1e-3
    np.testing.assert_allclose(points[0], points[1], atol=1e-9)


def test_joints_are_latched_at_the_files_reference_pose(tmp_path, pair):
    """A free joint on the body and a hinge (its ref 30 deg: qpos0, where MuJoCo draws the tip as written) driven
    by an actuator, read by a sensor, set by a keyframe: the target is the jointless tree's rigid body (the flat
    file's keypoints, mass, inertia and surface), the joints named and said once; the scene holds one joint, its
    own free joint."""
    text = TREE.format(joint='<joint name="hinge" type="hinge" axis="0 0 1" ref="30"/>')
    text = text.replace('<body name="target">', '<body name="target"><freejoint name="loose"/>')
    text = text.replace("</worldbody>", '</worldbody><actuator><motor joint="hinge"/></actuator><sensor>'
                        '<jointpos joint="hinge"/></sensor><keyframe><key qpos="0 0 0 1 0 0 0 1.2"/></keyframe>')
    path = tmp_path / "hinged.xml"
    path.write_text(text)
    mujoco.MjModel.from_xml_path(str(path))  # a file MuJoCo loads
    with pytest.warns(UserWarning, match=r"2 joint\(s\) latched .*loose, hinge"):
        hinged = load_target(str(path))
    with warnings.catch_warnings():  # the same file named another way: the same load, said once (it was twice)
        warnings.simplefilter("error")
        assert load_target(os.path.relpath(path)) is hinged
    flat = pair[1]
    assert hinged.latched_joints == ("loose", "hinge")
    np.testing.assert_allclose(hinged.keypoints_T_m, flat.keypoints_T_m, atol=1e-12)
    assert abs(hinged.mass_kg - 212.0) < 1e-9
    np.testing.assert_allclose(hinged.inertia_T_kg_m2, _composite(), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(hinged.mesh().vertices_T_m, flat.mesh().vertices_T_m, atol=1e-12)
    m = mujoco.MjModel.from_xml_string(scene_xml(hinged))
    b = m.body("target").id
    assert m.body_jntnum[b] == 1 and m.jnt_type[m.body_jntadr[b]] == mujoco.mjtJoint.mjJNT_FREE
    assert pair[0].latched_joints == ()


def _placed(model):
    """(model, data) with MuJoCo's kinematics done: every body, geom and site where MuJoCo puts it."""
    data = mujoco.MjData(model)
    mujoco.mj_kinematics(model, data)
    return model, data


def test_a_mesh_in_a_child_body_lands_where_mujoco_puts_it(tmp_path):
    """A wedge mesh (re-centred by MuJoCo on its own inertial frame) in a turned child body, itself turned: its
    vertices in T as MuJoCo places them in the file alone (mj_kinematics), to 1e-9 m, in the Target's surface and
    in the factory's scene (where the written pose, less the mesh's centring, is compiled again)."""
    path = tmp_path / "arm.xml"
    path.write_text(
        '<mujoco><asset><mesh name="wedge" vertex="-.3 -.2 -.1 .3 -.2 -.1 .3 .2 -.1 -.3 .2 -.1 -.3 -.2 .1 .3 -.2 .1"/>'
        '</asset><worldbody><body name="target"><inertial pos="0 0 0" mass="50" diaginertia="1 2 2.5"/>'
        '<geom type="box" size="0.4 0.4 0.4"/><site name="kp_1" pos="0.4 0.4 0.4"/><site name="kp_2" pos="-0.4 0.4 0.4"/>'
        '<site name="kp_3" pos="0.4 -0.4 0.4"/><body name="arm" pos="0 0 1.0" euler="0 45 0">'
        '<geom type="mesh" mesh="wedge" density="0" pos="0.1 0 0" euler="45 0 0"/><site name="kp_m" pos="0.1 -0.2 -0.1"/>'
        '</body></body></worldbody></mujoco>')
    m, d = _placed(mujoco.MjModel.from_xml_path(str(path)))

    def mesh_T(model, data):
        body = model.body("target").id
        g = next(g for g in range(model.ngeom) if model.geom_type[g] == mujoco.mjtGeom.mjGEOM_MESH)
        v0, nv = model.mesh_vertadr[model.geom_dataid[g]], model.mesh_vertnum[model.geom_dataid[g]]
        world = model.mesh_vert[v0:v0 + nv] @ data.geom_xmat[g].reshape(3, 3).T + data.geom_xpos[g]
        return (world - data.xpos[body]) @ data.xmat[body].reshape(3, 3)

    truth = mesh_T(m, d)
    t = load_target(str(path))
    near = np.min(np.linalg.norm(truth[:, None] - t.mesh().vertices_T_m[None], axis=2), axis=1)
    assert near.max() < 1e-9
    np.testing.assert_allclose(t.keypoints_T_m[-1], d.site_xpos[m.site("kp_m").id], atol=1e-12)
    s, ds = _placed(mujoco.MjModel.from_xml_string(scene_xml(t)))
    np.testing.assert_allclose(mesh_T(s, ds), truth, atol=1e-9)


def test_a_body_with_frames_is_labelled_where_mujoco_puts_its_sites(tmp_path):
    """MJCF <frame> elements in the body, one holding two keypoints ahead of the body's own in the file: every
    keypoint and geom of the factory's scene where MuJoCo puts them in the file alone (1e-9 m), names and order
    kept (the scene once wrote the frame's sites' numbers into the body's own: labels 0.9 m off)."""
    path = tmp_path / "framed.xml"
    path.write_text(
        '<mujoco><worldbody><body name="target"><inertial pos="0 0 0" mass="10" diaginertia="1 1.2 1.5"/>'
        '<geom name="core" type="box" size="0.5 0.4 0.3"/><frame pos="0 0 0.3" euler="0 0 30">'
        '<geom name="mast" type="box" size="0.05 0.05 0.4" pos="0 0 0.4"/><site name="kp_top" pos="0 0 0.8"/>'
        '<site name="kp_side" pos="0.05 0.05 0.8"/></frame><site name="kp_1" pos="0.5 0.4 0.3"/>'
        '<site name="kp_2" pos="-0.5 0.4 0.3"/><site name="kp_3" pos="0.5 -0.4 -0.3"/></body></worldbody></mujoco>')
    m, d = _placed(mujoco.MjModel.from_xml_path(str(path)))
    t = load_target(str(path))
    assert t.keypoint_names == ("top", "side", "1", "2", "3") and [g.name for g in t.geoms] == ["core", "mast"]
    s, ds = _placed(mujoco.MjModel.from_xml_string(scene_xml(t)))
    b = s.body("target").id
    to_T = lambda x: (x - ds.xpos[b]) @ ds.xmat[b].reshape(3, 3)  # noqa: E731
    for name in t.keypoint_sites:
        np.testing.assert_allclose(to_T(ds.site_xpos[s.site(name).id]), d.site_xpos[m.site(name).id], atol=1e-9)
    for name in ("core", "mast"):
        np.testing.assert_allclose(to_T(ds.geom_xpos[s.geom(name).id]), d.geom_xpos[m.geom(name).id], atol=1e-9)


def test_a_targets_sha256_covers_the_files_it_names(tmp_path):
    """The shipped targets name no other file: their sha256 is their bytes' (weights and datasets recorded before
    still match). A target with a mesh file: editing the mesh gives another sha256, also to the Target loaded again
    in the same process, so weights trained for the old one are refused; the edit undone gives the old one back."""
    for name in ("models/envisat.xml", "models/upper_stage.xml", "models/cubesat_3u.xml"):
        path = resolve_target_path(name)
        with open(path, "rb") as fh:
            assert target_sha256(path) == hashlib.sha256(fh.read()).hexdigest() == load_target(name).sha256
    (tmp_path / "meshes").mkdir()
    obj = tmp_path / "meshes" / "wedge.obj"
    wedge = "v -.3 -.2 -.1\nv .3 -.2 -.1\nv .3 .2 -.1\nv -.3 .2 -.1\nv -.3 -.2 .1\nv .3 -.2 .1\n" \
            "f 1 3 2\nf 1 4 3\nf 1 2 6\nf 1 6 5\nf 2 3 6\nf 4 1 5\nf 3 4 5\nf 3 5 6\n"
    obj.write_text(wedge)
    path = tmp_path / "wedge.xml"
    path.write_text('<mujoco><compiler meshdir="meshes"/><asset><mesh name="w" file="wedge.obj"/></asset><worldbody>'
                    '<body name="target"><inertial pos="0 0 0" mass="5" diaginertia="1 1 1"/><geom type="mesh" mesh="w"/>'
                    + "".join(f'<site name="kp_{i}" pos="{x}"/>' for i, x in
                              enumerate(["-.3 -.2 -.1", ".3 -.2 -.1", ".3 .2 -.1", "-.3 .2 -.1"]))
                    + "</body></worldbody></mujoco>")
    before = target_sha256(str(path))
    with open(path, "rb") as fh:
        assert before != hashlib.sha256(fh.read()).hexdigest()
    trained_for = {"name": "wedge", "sha256": before}
    require_weights_target("w.safetensors", trained_for, str(path))  # fits: nothing raised
    obj.write_text(wedge.replace("v .3 .2 -.1", "v .31 .2 -.1"))
    assert target_sha256(str(path)) != before and load_target(str(path)).sha256 != before
    with pytest.raises(InputError, match="not of target"):
        require_weights_target("w.safetensors", trained_for, str(path))
    obj.write_text(wedge)
    assert target_sha256(str(path)) == before == load_target(str(path)).sha256


def test_the_default_targets_name_with_another_file_of_that_name_here_warns(tmp_path, monkeypatch):
    """'models/envisat.xml' is the default's text (the packaged ENVISAT): a different file of that relative name in
    the working folder cannot be meant by it, and the user is told how to name that file; an identical copy (a
    checkout's own models folder) is silent."""
    import shutil
    import warnings

    packaged = resolve_target_path("models/envisat.xml")
    (tmp_path / "models").mkdir()
    monkeypatch.chdir(tmp_path)
    shutil.copy(packaged, tmp_path / "models" / "envisat.xml")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert resolve_target_path("models/envisat.xml") == packaged
    shutil.copy(resolve_target_path("models/upper_stage.xml"), tmp_path / "models" / "envisat.xml")
    with pytest.warns(UserWarning, match=r"is the packaged ENVISAT; .* give it as '\./models/envisat\.xml'"):
        assert resolve_target_path("models/envisat.xml") == packaged
    assert resolve_target_path("./models/envisat.xml") == str(tmp_path / "models" / "envisat.xml")
