"""Target files composed with MuJoCo's own means (each met by a user's file): a wing from another MJCF file
attached with <attach model=...>, its mesh in that file's own meshdir. Against MuJoCo's own reading of the file
alone, never against the code's output."""

import os
import struct

import mujoco
import numpy as np
import pytest

from envisat_pose.config import ConfigError
from envisat_pose.datagen.target_scene import scene_xml
from envisat_pose.target import load_target
from envisat_pose.target_assets import named_files, target_sha256

PYRAMID = np.array([[0.2, 0.2, 0.0], [-0.2, 0.2, 0.0], [-0.2, -0.2, 0.0], [0.2, -0.2, 0.0], [0.0, 0.0, 0.3]])
PYRAMID_FACES = [(0, 1, 4), (1, 2, 4), (2, 3, 4), (3, 0, 4), (0, 2, 1), (0, 3, 2)]


def _write_stl(path, scale: float = 1.0) -> None:
    """A square pyramid as a binary STL (MuJoCo reads its float32 vertices)."""
    with open(path, "wb") as fh:
        fh.write(b"\0" * 80 + struct.pack("<I", len(PYRAMID_FACES)))
        for face in PYRAMID_FACES:
            a, b, c = scale * PYRAMID[list(face)]
            n = np.cross(b - a, c - a)
            fh.write(struct.pack("<12fH", *(n / np.linalg.norm(n)), *a, *b, *c, 0))


def _composite(model, data):
    """Mass and inertia about the common CoM of every body but the world (the target at the world's origin)."""
    bodies = range(1, model.nbody)
    mass = sum(model.body_mass[b] for b in bodies)
    com = sum(model.body_mass[b] * data.xipos[b] for b in bodies) / mass
    inertia = np.zeros((3, 3))
    for b in bodies:
        R, r = data.ximat[b].reshape(3, 3), data.xipos[b] - com
        inertia += R @ np.diag(model.body_inertia[b]) @ R.T + model.body_mass[b] * (r @ r * np.eye(3) - np.outer(r, r))
    return mass, inertia


def _attaching_file(tmp_path):
    """main.xml: a bus with two copies of parts/wing.xml's body attached (prefixes kp_r_, kp_l_), the wing's horn
    a mesh in the wing file's own meshdir (parts/shapes/), which no folder of the main file holds."""
    (tmp_path / "parts" / "shapes").mkdir(parents=True)
    _write_stl(tmp_path / "parts" / "shapes" / "horn.stl")
    (tmp_path / "parts" / "wing.xml").write_text(
        '<mujoco model="wing"><compiler meshdir="shapes"/><asset><mesh name="horn" file="horn.stl"/>'
        '<material name="cell" rgba="0.1 0.1 0.6 1"/></asset><worldbody><body name="wing">'
        '<geom type="box" size="0.6 0.02 0.3" material="cell" density="50"/>'
        '<geom type="mesh" mesh="horn" pos="0.6 0 0" euler="0 90 0" rgba="1 1 1 1" density="50"/>'
        '<site name="kp_tip" pos="0.6 0.02 0.3"/><site name="kp_horn" pos="0.9 0 0"/></body></worldbody></mujoco>')
    path = tmp_path / "main.xml"
    path.write_text(
        '<mujoco model="attached"><asset><model name="wing" file="parts/wing.xml"/></asset><worldbody>'
        '<body name="target"><geom type="box" size="0.4 0.4 0.4" rgba="0.7 0.7 0.7 1" density="100"/>'
        '<site name="kp_a" pos="0.4 0.4 0.4"/><site name="kp_b" pos="-0.4 -0.4 0.4"/>'
        '<frame pos="1 0 0"><attach model="wing" body="wing" prefix="kp_r_"/></frame>'
        '<frame pos="-1 0 0" euler="0 0 180"><attach model="wing" body="wing" prefix="kp_l_"/></frame>'
        '</body></worldbody></mujoco>')
    return str(path)


def test_an_attached_models_mesh_is_read_from_that_models_folder(tmp_path):
    """MuJoCo reads an attached model's mesh relative to that model's file and meshdir: the Target and the
    factory's scene hold the shape MuJoCo gives the file alone (keypoints 1e-12 m, mass and inertia 1e-9
    relative, the scene's horns where MuJoCo puts them to 1e-6 m, its 6-digit quaternions), from any working
    folder. They were refused: 'Error opening file .../horn.stl' (the main file's folder and meshdir)."""
    path = _attaching_file(tmp_path)
    alone = mujoco.MjModel.from_xml_path(path)
    data = mujoco.MjData(alone)
    mujoco.mj_forward(alone, data)
    cwd = os.getcwd()
    os.chdir(tmp_path / "parts")  # neither the main file's folder nor the wing's meshdir
    try:
        target = load_target(path)
        scene = mujoco.MjModel.from_xml_string(scene_xml(target))
    finally:
        os.chdir(cwd)
    sites = [s for s in range(alone.nsite) if alone.site(s).name.startswith("kp_")]
    assert list(target.keypoint_sites) == [alone.site(s).name for s in sites]
    np.testing.assert_allclose(target.keypoints_T_m, data.site_xpos[sites], atol=1e-12)
    mass, inertia = _composite(alone, data)
    assert abs(target.mass_kg - mass) < 1e-9 * mass
    np.testing.assert_allclose(target.inertia_T_kg_m2, inertia, atol=1e-9 * np.abs(inertia).max())
    sd = mujoco.MjData(scene)
    mujoco.mj_forward(scene, sd)
    b = scene.body("target").id
    for name in ("kp_r_horn", "kp_l_horn"):
        g_alone = next(g for g in range(alone.ngeom) if alone.geom_dataid[g] == alone.mesh(name).id)
        g_scene = next(g for g in range(scene.ngeom) if scene.geom_dataid[g] == scene.mesh("target/" + name).id)
        in_T = sd.xmat[b].reshape(3, 3).T @ (sd.geom_xpos[g_scene] - sd.xpos[b])
        np.testing.assert_allclose(in_T, data.geom_xpos[g_alone], atol=1e-6)
        assert scene.mesh_vertnum[scene.geom_dataid[g_scene]] == alone.mesh_vertnum[alone.mesh(name).id]


def test_an_attached_models_files_are_part_of_the_target(tmp_path):
    """The attached wing's file and its mesh are files the target names: an edit to either is another target
    (another sha256; weights trained before are refused). The wing's file was left out, its mesh sought in the
    main file's folder: a wing edited kept the sha256."""
    path = _attaching_file(tmp_path)
    wing, horn = tmp_path / "parts" / "wing.xml", tmp_path / "parts" / "shapes" / "horn.stl"
    assert {str(wing), str(horn)} <= set(named_files(path))
    before = target_sha256(path)
    wing.write_text(wing.read_text().replace('size="0.6 0.02 0.3"', 'size="0.6 0.03 0.3"'))
    edited = target_sha256(path)
    assert edited != before
    _write_stl(horn, scale=1.5)
    assert target_sha256(path) != edited


def test_a_files_statistic_does_not_loosen_the_centre_of_mass_check(tmp_path):
    """A file's <statistic extent> (a viewer's setting) leaves the centre of mass's tolerance at a share of the size
    MuJoCo computes from the geometry: a bus 1 mm off its origin is refused as it is without one (with extent 1e5
    it was taken, its CoM moved to the origin in the truth, the labels 1 mm off the dynamics)."""
    body = ('<worldbody><body name="target"><geom type="box" size="0.5 0.4 0.3" pos="0.001 0 0" density="100"/>'
            + "".join(f'<site name="kp_{i}" pos="{x}"/>' for i, x in
                      enumerate(["0.5 0.4 0.3", "-0.5 0.4 0.3", "0.5 -0.4 0.3", "0.5 0.4 -0.3"]))
            + "</body></worldbody>")
    for name, stated in (("plain", ""), ("stated", '<statistic extent="100000" center="0 0 0"/>')):
        path = tmp_path / f"{name}.xml"
        path.write_text(f"<mujoco>{stated}{body}</mujoco>")
        assert mujoco.MjModel.from_xml_path(str(path)).body_ipos[1][0] == pytest.approx(0.001, abs=1e-12)
        with pytest.raises(ConfigError, match="centre of mass at the body's origin"):
            load_target(str(path))


def test_keypoints_behind_an_attach_prefix_are_named_in_the_refusal(tmp_path):
    """The wing attached under prefixes that do not start with kp_ (h_r_, h_l_): its sites are h_r_kp_tip and the
    like, not keypoints, and the refusal for too few keypoints names them and says what to change (it said 'found
    2' alone)."""
    path = _attaching_file(tmp_path)
    text = open(path).read().replace('prefix="kp_r_"', 'prefix="h_r_"').replace('prefix="kp_l_"', 'prefix="h_l_"')
    open(path, "w").write(text)
    with pytest.raises(ConfigError) as err:
        load_target(path)
    message = str(err.value)
    assert "(found 2; 4 site(s) hold 'kp_' after another prefix ('h_r_kp_tip'" in message
    assert "<attach prefix> before keypoint sites should itself start with 'kp_'" in message
    few = tmp_path / "few.xml"  # too few keypoints and no such site: the other sites named (a prefix forgotten)
    for other, said in (('<site name="tip"/>', "; not keypoints: its site(s) 'tip', whose names do not start with "
                                               "'kp_' (case matters)"), ("", "")):  # no other site: the count alone
        few.write_text('<mujoco><worldbody><body name="target"><geom type="box" size="0.3 0.3 0.3" density="100"/>'
                       f'<site name="kp_a" pos="0.3 0.3 0.3"/><site name="kp_b" pos="-0.3 0.3 0.3"/>{other}'
                       '</body></worldbody></mujoco>')
        with pytest.raises(ConfigError) as err:
            load_target(str(few))
        assert str(err.value).endswith(f"(found 2{said})")
