"""Target files in forms a user writes them (each met by a new user's files): a <frame childclass>, a cube texture
of six files through texturedir, mass properties MuJoCo computes or balances itself, an <option> from a template,
an empty keypoint name. Each against MuJoCo's own reading of the file alone, never against the code's output."""

import os
import warnings

import cv2
import mujoco
import numpy as np
import pytest

from envisat_pose.config import ConfigError, InputError
from envisat_pose.datagen.target_scene import scene_xml
from envisat_pose.geometry import model_path
from envisat_pose.target import load_target
from envisat_pose.target_assets import named_files, target_sha256

SITES = "".join(f'<site name="kp_{i}" pos="{x}"/>' for i, x in
                enumerate(["0.3 0.3 0.3", "-0.3 0.3 0.3", "0.3 -0.3 -0.3", "-0.3 -0.3 0.3"]))
BUS = '<geom name="bus" type="box" size="0.3 0.3 0.3" rgba="0.7 0.7 0.7 1"/>'


def _placed(model):
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    return data


def _geoms_in_T(model, names):
    """{name: (type, size, rgba, position in T, rotation in T)} of body 'target''s named geoms."""
    d, b = _placed(model), model.body("target").id
    R_b, p_b = d.xmat[b].reshape(3, 3), d.xpos[b]
    out = {}
    for n in names:
        g = model.geom(n).id
        out[n] = (int(model.geom_type[g]), model.geom_size[g].copy(), model.geom_rgba[g].copy(),
                  (d.geom_xpos[g] - p_b) @ R_b, R_b.T @ d.geom_xmat[g].reshape(3, 3))
    return out


def test_a_frames_childclass_gives_its_geoms_their_class(tmp_path):
    """A frame's childclass reaches the geoms inside it, through a nested frame with none of its own, but not one
    that names its class: the factory's scene holds the boxes MuJoCo draws for the file alone (it once drew a
    sphere, the frame's class dropped)."""
    path = tmp_path / "framed.xml"
    path.write_text(
        '<mujoco><compiler angle="degree"/><default><default class="plate"><geom type="box" size="0.3 0.2 0.01" '
        'rgba="0.2 0.2 0.6 1"/></default><default class="rod"><geom type="capsule" size="0.02 0.2" '
        'rgba="0.9 0.1 0.1 1"/></default></default><worldbody><body name="target">'
        '<inertial pos="0 0 0" mass="10" diaginertia="1 1 1.5"/>' + BUS +
        '<frame pos="0 0.6 0" euler="0 0 90" childclass="plate"><geom name="panel"/>'
        '<frame pos="0.1 0 0.2" euler="30 0 0"><geom name="inner"/><geom name="stick" class="rod"/></frame></frame>'
        + SITES + '</body></worldbody></mujoco>')
    names = ("bus", "panel", "inner", "stick")
    alone = _geoms_in_T(mujoco.MjModel.from_xml_path(str(path)), names)
    scene = _geoms_in_T(mujoco.MjModel.from_xml_string(scene_xml(load_target(str(path)))), names)
    assert alone["panel"][0] == alone["inner"][0] == mujoco.mjtGeom.mjGEOM_BOX
    assert alone["stick"][0] == mujoco.mjtGeom.mjGEOM_CAPSULE
    for n in names:
        assert scene[n][0] == alone[n][0], n
        for a, b in zip(scene[n][1:], alone[n][1:]):
            np.testing.assert_allclose(a, b, atol=1e-6, err_msg=n)  # rgba is written to 6 digits


def _cube_target(folder) -> str:
    tex = folder / "textures"
    tex.mkdir()
    for i, face in enumerate(("right", "left", "up", "down", "front", "back")):
        cv2.imwrite(str(tex / f"{face}.png"), np.full((8, 8, 3), 30 * i, np.uint8))
    faces = " ".join(f'file{face}="{face}.png"' for face in ("right", "left", "up", "down", "front", "back"))
    path = folder / "cubed.xml"
    path.write_text(f'<mujoco><compiler texturedir="textures"/><asset><texture name="c" type="cube" {faces}/>'
                    '<material name="m" texture="c"/></asset><worldbody><body name="target">'
                    '<inertial pos="0 0 0" mass="40" diaginertia="2 2 2"/>'
                    f'<geom name="bus" type="box" size="0.3 0.3 0.3" material="m"/>{SITES}</body></worldbody>'
                    '</mujoco>')
    return str(path)


def test_a_cube_texture_of_six_files_is_read_from_any_folder(tmp_path, monkeypatch):
    """A cube texture given face by face through texturedir: the scene compiles with the run started in another
    folder, its six faces are among the files the target names, and editing one face makes another target."""
    home = tmp_path / "home"
    home.mkdir()
    path = _cube_target(home)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    model = mujoco.MjModel.from_xml_string(scene_xml(load_target(path)))
    assert model.ntex >= 1
    faces = {os.path.join(str(home), "textures", f"{f}.png") for f in ("right", "left", "up", "down", "front", "back")}
    assert faces <= set(named_files(path))
    before = target_sha256(path)
    cv2.imwrite(str(home / "textures" / "up.png"), np.full((8, 8, 3), 200, np.uint8))
    assert target_sha256(path) != before


def _inertia_T(model):
    b = model.body("target").id
    R = np.zeros(9)
    mujoco.mju_quat2Mat(R, model.body_iquat[b])
    R = R.reshape(3, 3)
    return model.body_mass[b], R @ np.diag(model.body_inertia[b]) @ R.T


@pytest.mark.parametrize("compiler", ['inertiafromgeom="true"', 'balanceinertia="true"'])
def test_mass_properties_are_the_ones_mujoco_compiles(tmp_path, compiler):
    """inertiafromgeom='true' sets a stated <inertial> aside (MuJoCo's mass from the geoms' density), and
    balanceinertia='true' mends moments that break the triangle inequality: the Target takes what MuJoCo
    compiles, where it once checked the stated numbers and refused the file."""
    path = tmp_path / "massy.xml"
    path.write_text(f'<mujoco><compiler {compiler}/><worldbody><body name="target">'
                    '<inertial pos="0 0 0" mass="100" diaginertia="1 2 9"/>'
                    '<geom name="bus" type="box" size="0.3 0.3 0.3" density="500"/>' + SITES +
                    '</body></worldbody></mujoco>')
    mass, inertia = _inertia_T(mujoco.MjModel.from_xml_path(str(path)))
    target = load_target(str(path))
    assert target.mass_kg == pytest.approx(mass, rel=1e-9)
    np.testing.assert_allclose(target.inertia_T_kg_m2, inertia, rtol=1e-9, atol=1e-12)
    if "inertiafromgeom" in compiler:
        assert mass == pytest.approx(500 * 0.6 ** 3)  # the box's volume times its density, not the stated 100 kg
    else:
        a, b, c = sorted(np.linalg.eigvalsh(inertia))
        assert c <= a + b + 1e-9  # balanced by MuJoCo (stated 1, 2, 9)


@pytest.mark.parametrize("own,same", [
    ('<option timestep="0.002" gravity="0 0 -9.81"/>',  # a MuJoCo template's physics
     lambda scene, envisat: scene.opt.timestep == envisat.opt.timestep
     and np.array_equal(scene.opt.gravity, envisat.opt.gravity)),
    ('<visual><global fovy="10"/><map znear="0.5" zfar="2"/></visual>',  # a viewer's clip planes and field of view
     lambda scene, envisat: scene.vis.global_.fovy == envisat.vis.global_.fovy
     and scene.vis.map.zfar == envisat.vis.map.zfar),
], ids=["option", "visual"])
def test_a_files_own_option_or_visual_does_not_clash_with_the_scene(own, same, tmp_path, monkeypatch):
    """A file holding its own <option> (from a MuJoCo template) or <visual>: the scene keeps ENVISAT's, with no
    warning printed and no MUJOCO_LOG.TXT written into the folder the run started in (MuJoCo's attach warned of an
    'Attach conflict' and wrote its log there)."""
    path = tmp_path / "own.xml"
    path.write_text(f'<mujoco>{own}<worldbody><body name="target">'
                    '<inertial pos="0 0 0" mass="10" diaginertia="1 1.2 1.5"/>' + BUS + SITES +
                    '</body></worldbody></mujoco>')
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    monkeypatch.chdir(run_dir)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        scene = mujoco.MjModel.from_xml_string(scene_xml(load_target(str(path))))
    assert same(scene, mujoco.MjModel.from_xml_path(model_path()))
    assert os.listdir(run_dir) == []


def test_an_empty_keypoint_name_is_refused(tmp_path):
    path = tmp_path / "blank.xml"
    path.write_text('<mujoco><worldbody><body name="target"><inertial pos="0 0 0" mass="10" diaginertia="1 1 1"/>'
                    + BUS + SITES + '<site name="kp_" pos="0.3 0.3 -0.3"/></body></worldbody></mujoco>')
    with pytest.raises((ConfigError, InputError), match="non-empty names"):
        load_target(str(path))


@pytest.mark.parametrize("tree", [False, True], ids=["alone", "with-children"])
def test_a_mocap_body_is_a_free_target_drawn_where_mujoco_draws_it(tmp_path, tree):
    """A body a viewer moves by hand (mocap="true") is, alone, drawn where it is written: the scene takes it as
    the free target (MuJoCo refused the scene's free joint on it, a traceback), its geoms where MuJoCo puts them."""
    arms = ('<body pos="0 0 0.4"><geom name="up" type="sphere" size="0.1"/></body>'
            '<body pos="0 0 -0.4"><geom name="down" type="sphere" size="0.1"/></body>') if tree else ""
    path = tmp_path / "mocap.xml"
    path.write_text('<mujoco><worldbody><body name="target" mocap="true" pos="1 2 3">' + BUS + SITES + arms +
                    '</body></worldbody></mujoco>')
    names = ("bus", "up", "down") if tree else ("bus",)
    alone = _geoms_in_T(mujoco.MjModel.from_xml_path(str(path)), names)
    scene_model = mujoco.MjModel.from_xml_string(scene_xml(load_target(str(path))))
    scene = _geoms_in_T(scene_model, names)
    assert scene_model.body("target").mocapid[0] == -1 and scene_model.body("target").jntnum[0] == 1
    for n in names:
        np.testing.assert_allclose(scene[n][3], alone[n][3], atol=1e-9)


@pytest.mark.parametrize("where, kind, words", [
    ("target", "plane", "is a plane"), ("child", "plane", "is a plane"), ("target", "hfield", "is a height field")])
def test_a_geom_the_target_cannot_read_is_refused_in_one_line(tmp_path, where, kind, words):
    """A plane geom (infinite; MuJoCo refuses it in a moving body) on the target or a child, or a height field (drawn,
    but no part of the surface the labels' visibility reads: a keypoint on it was refused as 1 m from every drawn
    geom): one line naming the body, the geom and what to write instead (the plane was the scene's traceback)."""
    sail = ('<geom name="sail" type="plane" size="1 1 0.1"/>' if kind == "plane" else
            '<geom name="sail" type="hfield" hfield="h" mass="0"/>')
    body = sail if where == "target" else f'<body name="arm" pos="0 0 0.4">{sail}</body>'
    path = tmp_path / "plane.xml"
    path.write_text('<mujoco><asset><hfield name="h" nrow="2" ncol="2" size="1 1 0.1 0.05" elevation="1 1 1 1"/>'
                    '</asset><worldbody><body name="target">' + BUS + SITES + body + '</body></worldbody></mujoco>')
    with pytest.raises(ConfigError) as err:
        load_target(str(path))
    text = str(err.value)
    named = "'target'" if where == "target" else "'arm'"
    assert f"body {named}" in text and f"'sail' {words}" in text and "\n" not in text


@pytest.mark.parametrize("where", ["world", "target"])
def test_a_camera_named_as_the_factorys_does_not_make_the_file_a_scene(tmp_path, where):
    """A file with a camera of its own named chaser_cam (the factory's camera's name), in the world or on the
    target, is a target file like any other: the scene holds the factory's chaser, Earth and free joint, and the
    target where MuJoCo puts it (it was taken as its own whole scene: a KeyError traceback in the renderer)."""
    cam = '<camera name="chaser_cam" pos="3 3 3" xyaxes="-1 1 0 -1 -1 2"/>'
    path = tmp_path / "cam.xml"
    path.write_text('<mujoco><worldbody>' + (cam if where == "world" else "") + '<body name="target" pos="0 0 1">'
                    '<freejoint name="float"/>' + (cam if where == "target" else "") + BUS + SITES +
                    '</body></worldbody></mujoco>')
    with pytest.warns(UserWarning, match="latched"):  # its free joint
        target = load_target(str(path))
    assert not target.own_scene
    scene = mujoco.MjModel.from_xml_string(scene_xml(target))
    for kind, name in (("joint", "target_free"), ("body", "chaser"), ("light", "sun")):
        getattr(scene, kind)(name)  # KeyError where the scene lacks it
    np.testing.assert_allclose(_geoms_in_T(scene, ("bus",))["bus"][3],
                               _geoms_in_T(mujoco.MjModel.from_xml_path(str(path)), ("bus",))["bus"][3], atol=1e-12)
    assert load_target(model_path()).own_scene
