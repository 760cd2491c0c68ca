"""The fast visibility table (target_visibility.py) made by batched ray casts is the table the plain casts give.

References independent of the code under test: a target written here with a geom of each kind MuJoCo casts rays
at (box, cylinder, sphere, capsule, mesh), a veil of alpha 0.3 (hides nothing) and a boom in the appendage group,
its body moved and turned in the file; the plain casts one ray and one geom at a time (mju_rayGeom / mj_rayMesh
on the file compiled here, the occluders named here); each cell's nearest direction by the argmax over all.
"""

import mujoco
import numpy as np
import pytest

from envisat_pose import target_visibility
from envisat_pose.target import RAY_ABS_TOL_M, load_target
from envisat_pose.target_shape import fibonacci_directions
from envisat_pose.target_visibility import build_visibility_table, direction_cells

MIXED = """<mujoco model="mixed">
 <asset><mesh name="wedge" vertex="0 0 0  0.4 0 0  0 0.4 0  0 0 0.4"/>
  <material name="grey" rgba="0.6 0.6 0.6 1"/></asset>
 <worldbody><body name="target" pos="0.3 -0.2 0.1" quat="0.9 0.1 0.3 0.2">
  <inertial pos="0 0 0" mass="20" diaginertia="1 2 2.5"/>
  <geom name="plate" type="box" size="0.5 0.3 0.05" rgba="0.7 0.7 0.7 1"/>
  <geom name="rod" type="cylinder" fromto="0 0 0.05 0 0 0.6" size="0.05" material="grey"/>
  <geom name="ball" type="sphere" pos="0.3 0 -0.2" size="0.12" rgba="0.8 0.2 0.2 1"/>
  <geom name="arm" type="capsule" fromto="-0.3 0 -0.05 -0.3 0 -0.4" size="0.04" rgba="0.2 0.8 0.2 1"/>
  <geom name="wedge" type="mesh" mesh="wedge" pos="-0.2 -0.2 0.05" rgba="0.9 0.9 0.2 1"/>
  <geom name="veil" type="box" pos="0 0 0.3" size="0.3 0.3 0.01" rgba="0.5 0.5 1 0.3"/>
  <geom name="boom" type="box" pos="0 0 -0.3" size="0.6 0.05 0.02" group="4" rgba="0.3 0.3 0.3 1"/>
  <site name="kp_a" pos="0.5 0.3 0.05"/><site name="kp_b" pos="-0.5 0.3 0.05"/>
  <site name="kp_c" pos="-0.5 -0.3 -0.05"/><site name="kp_d" pos="0.5 -0.3 0.05"/>
  <site name="kp_top" pos="0 0 0.6"/><site name="kp_ball" pos="0.3 0 -0.32"/>
 </body></worldbody>
</mujoco>"""
OCCLUDERS = ("plate", "rod", "ball", "arm", "wedge")  # opaque and drawn; the boom too with appendages


@pytest.fixture(scope="module")
def mixed(tmp_path_factory):
    path = tmp_path_factory.mktemp("vis") / "mixed.xml"
    path.write_text(MIXED)
    return str(path)


def _plain_visible(path, origins_T_m, points_T_m, appendages):
    """(P, K) bool: each ray from an origin to a point cast geom by geom (mju_rayGeom, mj_rayMesh) in the file
    compiled here, visible where no occluder is met before the point (less 0.1 mm plus 1e-6 of the range)."""
    model = mujoco.MjModel.from_xml_path(path)
    data = mujoco.MjData(model)
    mujoco.mj_kinematics(model, data)
    body = model.body("target").id
    R_W_T, p_W = data.xmat[body].reshape(3, 3), data.xpos[body]
    names = OCCLUDERS + (("boom",) if appendages else ())
    geoms = [model.geom(n).id for n in names]
    out = np.zeros((len(origins_T_m), len(points_T_m)), bool)
    for i, c in enumerate(origins_T_m):
        pnt = p_W + R_W_T @ c
        for k, x in enumerate(points_T_m):
            d = R_W_T @ (x - c)
            vec, rng = d / np.linalg.norm(d), np.linalg.norm(x - c)
            hit = np.inf
            for g in geoms:
                if model.geom_type[g] == mujoco.mjtGeom.mjGEOM_MESH:
                    h = mujoco.mj_rayMesh(model, data, g, pnt, vec)
                else:
                    h = mujoco.mju_rayGeom(data.geom_xpos[g], data.geom_xmat[g], model.geom_size[g], pnt, vec,
                                           int(model.geom_type[g]))
                hit = min(hit, h) if h >= 0 else hit
            out[i, k] = hit >= rng - (RAY_ABS_TOL_M + 1e-6 * rng)
    return out


@pytest.mark.parametrize("appendages", [False, True])
def test_the_table_is_the_one_the_plain_casts_give(mixed, monkeypatch, appendages):
    """The table over 256 directions (the module's count turned down to keep this fast) at its four ranges: each
    cell's visibility the same as the plain casts from that direction and range give, widened to the nearest
    directions as the table says; the boom hides keypoints only with appendages, the veil none."""
    monkeypatch.setattr(target_visibility, "TABLE_DIRECTIONS", 256)
    t = load_target(mixed)
    table = build_visibility_table(t, appendages)
    origins = table.dirs_T[None] * table.ranges_m[:, None, None]  # (B, N, 3)
    plain = _plain_visible(mixed, origins.reshape(-1, 3), t.keypoints_T_m, appendages).reshape(4, 256, -1)
    nearest = np.argsort(-(table.dirs_T @ table.dirs_T.T), axis=1)[:, :target_visibility.TABLE_NEIGHBOURS + 1]
    np.testing.assert_array_equal(table.visible, plain[:, nearest].any(axis=2))
    np.testing.assert_array_equal(t.visible_from(origins, appendages), plain)
    assert (~plain).sum() > 300  # the casts meet occluders: the comparison is not of all-visible tables
    if appendages:  # the boom under the plate hides the keypoints below it from some views
        assert (plain < _plain_visible(mixed, origins.reshape(-1, 3), t.keypoints_T_m, False).reshape(plain.shape)
                ).any()


def test_visible_from_takes_many_positions_at_once(mixed):
    """Positions (2, 3, 3) in T give (2, 3, K), each row what that position alone gives, and the rows differ."""
    t = load_target(mixed)
    rng = np.random.default_rng(7)
    c = rng.standard_normal((2, 3, 3))
    c *= 2.0 / np.linalg.norm(c, axis=-1, keepdims=True)
    many = t.visible_from(c, True)
    assert many.shape == (2, 3, t.num_keypoints)
    for i, j in np.ndindex(2, 3):
        np.testing.assert_array_equal(many[i, j], t.visible_from(c[i, j], True))
    assert len({tuple(row) for row in many.reshape(6, -1)}) > 1


def test_the_table_is_cast_in_one_batch(mixed, monkeypatch):
    """Building the table casts all its rays in one call of the Target's casts (it made one per direction and
    range: 8,192 Python-level casts, the ~6-12 s it cost)."""
    import envisat_pose.target as target_module

    calls = []
    cast = target_module.ray_hits_m
    monkeypatch.setattr(target_module, "ray_hits_m", lambda *a: calls.append(a[2].shape) or cast(*a))
    t = load_target(mixed)
    build_visibility_table(t, False)
    assert calls == [(len(target_visibility.TABLE_RANGES_REACHES), target_visibility.TABLE_DIRECTIONS, 3)]


@pytest.mark.parametrize("dirs", [fibonacci_directions(2048), fibonacci_directions(37),
                                  np.random.default_rng(2).standard_normal((500, 3))])
def test_each_cell_finds_the_nearest_direction_of_all(dirs):
    """Each cell's direction is the argmax of the dot product with the cell's centre over every direction (the
    first of equals), for the table's Fibonacci sphere, a sparse one, and random directions."""
    dirs = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
    rows = 64
    polar = (np.arange(rows) + 0.5) * np.pi / rows
    azimuth = (np.arange(2 * rows) + 0.5) * np.pi / rows - np.pi
    p, a = np.meshgrid(polar, azimuth, indexing="ij")
    centres = np.stack([np.sin(p) * np.cos(a), np.sin(p) * np.sin(a), np.cos(p)], axis=-1).reshape(-1, 3)
    np.testing.assert_array_equal(direction_cells(dirs, rows), np.argmax(centres @ dirs.T, axis=1).reshape(p.shape))
