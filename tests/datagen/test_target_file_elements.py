"""What a user's own target file may hold beyond geoms and keypoints, and what the factory makes of it: its kp_
sites (labels, never drawn), its lights (the scene lights the target, not the file; a <light> in a <frame> or a
child body once stopped every verb), geoms of alpha 0 (MuJoCo draws none and its mj_ray meets none: they hide
no keypoint).

References independent of the code under test: the test's own files read by MuJoCo alone (mj_ray, its compiled
lights), the rendered mask at each keypoint's pixel.
"""

import mujoco
import numpy as np
import pytest

CUBE_HALF_M = 0.05
# a 10 cm cube's face centres (one on each face, off every silhouette edge) and two corners
FACE_KEYPOINTS = {f"{s}{a}": tuple(CUBE_HALF_M * (1 if s == "p" else -1) * (i == k) for k in range(3))
                  for i, a in enumerate("xyz") for s in "pm"}
FACE_KEYPOINTS.update({"c0": (CUBE_HALF_M,) * 3, "c1": (-CUBE_HALF_M,) * 3})


def _cube_xml(extra_body: str = "", extra_asset: str = "") -> str:
    sites = "".join(f'<site name="kp_{n}" pos="{p[0]} {p[1]} {p[2]}"/>' for n, p in FACE_KEYPOINTS.items())
    return (f'<mujoco model="cube10"><asset>{extra_asset}</asset><worldbody><body name="target">'
            f'<inertial pos="0 0 0" mass="1" diaginertia="0.002 0.002 0.002"/>'
            f'<geom name="cube" type="box" size="{CUBE_HALF_M} {CUBE_HALF_M} {CUBE_HALF_M}" rgba="0.7 0.7 0.7 1"/>'
            f'{sites}{extra_body}</body></worldbody></mujoco>')


def test_keypoint_sites_are_not_drawn_into_the_image_or_the_mask(tmp_path):
    """A 10 cm cube 0.6 m away at 256 px (a kp_ site of MuJoCo's default group 0 and size: a ball 8 px across on
    the keypoint): at every keypoint the label calls visible, the 3 x 3 pixels about its projection are the cube's
    in the mask (the site drawn would cover them with a value of 0) and the lit image is the face's own grey (the
    ball's shading differs)."""
    from envisat_pose.datagen.render import SceneRenderer
    from envisat_pose.datagen.render_view import View
    from envisat_pose.target import load_target

    path = tmp_path / "cube.xml"
    path.write_text(_cube_xml())
    target = load_target(str(path))
    renderer = SceneRenderer(256, shadows=False, target=str(path))
    checked = 0
    try:
        rng = np.random.default_rng(5)
        for _ in range(3):
            q = rng.normal(size=4)
            R = np.zeros(9)
            mujoco.mju_quat2Mat(R, q / np.linalg.norm(q))
            out = renderer.render(View(np.array([0.0, 0.6, 0.0]), R.reshape(3, 3), np.array([0.3, -1.0, 0.2])))
            uvw = out.corners_K_m @ renderer.K.T
            px = np.rint(uvw[:, :2] / uvw[:, 2:3]).astype(int)
            visible = target.visible(out.R_K_from_T, out.t_K_from_T_m)
            value = renderer.mask_values["cube"]
            for k in np.flatnonzero(visible):
                u, v = px[k]
                if not FACE_KEYPOINTS[target.keypoint_names[k]].count(0.0) == 2:
                    continue  # a corner: on the silhouette, its window part background
                window = out.mask_u8[v - 1:v + 2, u - 1:u + 2]
                assert np.all(window == value), (target.keypoint_names[k], window)
                checked += 1
    finally:
        renderer.close()
    assert checked >= 6


LIGHTS = {
    "on the body": '<light name="lamp" pos="0 0 0.5" dir="0 0 -1" diffuse="2 2 2"/>',
    "in a frame": '<frame pos="0 0 0.05" euler="0 0 30"><light name="lamp" pos="0 0 0.5" dir="0 0 -1"/></frame>',
    "on a child body": '<body name="mast" pos="0 0 0"><geom type="sphere" size="0.01" mass="0.001"/>'
                       '<light name="lamp" pos="0 0 0.5" dir="0 0 -1"/></body>',
}


@pytest.mark.parametrize("where", sorted(LIGHTS))
def test_a_light_on_the_target_is_left_out_of_the_scene(where, tmp_path):
    """A <light> on the target (MuJoCo compiles the file alone with it): the target loads and the factory's scene
    holds the scene's own lights only (before: the body's light lit the images; in a frame or on a child body the
    fused file carried a `quat` MuJoCo refuses on a light, and load or every verb stopped)."""
    from envisat_pose.datagen.target_scene import scene_xml
    from envisat_pose.target import load_target

    path = tmp_path / "lit.xml"
    path.write_text(_cube_xml(LIGHTS[where]))
    assert mujoco.MjModel.from_xml_path(str(path)).nlight == 1  # MuJoCo reads the file alone
    scene = mujoco.MjModel.from_xml_string(scene_xml(load_target(str(path))))
    envisat = mujoco.MjModel.from_xml_string(scene_xml(load_target()))
    assert sorted(scene.light(i).name for i in range(scene.nlight)) == \
        sorted(envisat.light(i).name for i in range(envisat.nlight))


GHOSTS = {"rgba": ('<geom name="ghost" type="box" pos="0 0 0.1" size="0.05 0.05 0.01" rgba="1 1 1 0"/>', ""),
          "material": ('<geom name="ghost" type="box" pos="0 0 0.1" size="0.05 0.05 0.01" material="clear"/>',
                       '<material name="clear" rgba="1 1 1 0"/>')}


@pytest.mark.parametrize("form", sorted(GHOSTS))
def test_a_geom_of_alpha_0_hides_no_keypoint(form, tmp_path):
    """A plate of alpha 0 (its rgba's, or its material's) between the camera and the cube's top: MuJoCo draws it
    not and its mj_ray passes through it, so the labels call the top's keypoint visible, as mj_ray over the file
    alone does (before: hidden behind a plate no image shows)."""
    from envisat_pose.target import load_target

    path = tmp_path / "ghost.xml"
    body, asset = GHOSTS[form]
    path.write_text(_cube_xml(body, asset))
    target = load_target(str(path))
    model = mujoco.MjModel.from_xml_path(str(path))
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    camera = np.array([0.01, 0.02, 1.0])
    k = target.keypoint_names.index("pz")
    point = target.keypoints_T_m[k]
    dist = np.linalg.norm(point - camera)
    hit = mujoco.mj_ray(model, data, camera, (point - camera) / dist, None, 1, -1, np.zeros(1, np.int32))
    assert hit >= dist - 1e-4  # MuJoCo: nothing before the keypoint
    assert target.visible_from(camera)[k]
    assert not target.drawn()[[g.name for g in target.geoms].index("ghost")]


def test_an_appearance_keeps_a_geom_of_alpha_0_undrawn(tmp_path):
    """The plate of a material of alpha 0 above the cube, the camera looking down on both, an appearance drawn
    over every geom's material (random mode's): the mask holds the cube and never the plate, as MuJoCo draws the
    file alone (before: the appearance's material made it opaque)."""
    from envisat_pose.datagen.appearance import OWN_CLASS, Appearance, GeomAppearance
    from envisat_pose.datagen.render import SceneRenderer
    from envisat_pose.datagen.render_view import View

    path = tmp_path / "ghost.xml"
    path.write_text(_cube_xml(*GHOSTS["material"]))
    renderer = SceneRenderer(128, shadows=False, texture_set_size=1, target=str(path))
    try:
        look = {g: GeomAppearance(OWN_CLASS, 0, (0.8, 0.8, 0.8), 0.5, 0.5, 0.0) for g in ("cube", "ghost")}
        down = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])  # T's +z toward the camera
        out = renderer.render(View(np.array([0.0, 0.6, 0.0]), down, np.array([0.0, -1.0, 0.3]),
                                   appearance=Appearance(look)))
        values = set(np.unique(out.mask_u8).tolist())
        assert renderer.mask_values["cube"] in values and renderer.mask_values["ghost"] not in values, values
    finally:
        renderer.close()
