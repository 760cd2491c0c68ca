"""Semi-transparent geoms (0 < alpha < 1) and keypoint visibility: a keypoint is hidden only by an opaque geom
(alpha 1, as MuJoCo's renderer takes it: the geom's own rgba where it is not MuJoCo's default, else its
material's), as the rendered image shows it; the labels and the filter's visibility table agree.

Reference independent of the code under test: MuJoCo's rendered image of the test's own file. Each keypoint's
surface is drawn once light grey and once black (the model's colour changed between two renders of one view); the
difference at the keypoint's pixel is the light of its own surface reaching the camera, measured against that of
a keypoint with nothing in front. The factory draws transparent geoms additively (its Earth's pass), so that
light arrives whole through a veil of any alpha below 1 and not at all through an opaque one.
"""

import numpy as np
import pytest

from envisat_pose.attitude import dcm_to_mrp
from envisat_pose.target import load_target

# one veil in front of each keypoint but the last: (the veil's attributes, what MuJoCo's renderer draws it as)
VEILS = (('rgba="0.2 0.2 0.2 0.3"', "transparent: its own rgba"),
         ('material="clear"', "transparent: its material's alpha 0.3"),
         ('material="solid" rgba="0.2 0.2 0.2 0.3"', "transparent: its rgba overrides the opaque material"),
         ('material="clear" rgba="0.2 0.2 0.2 1"', "opaque: its rgba overrides the transparent material"),
         ('rgba="0.2 0.2 0.2 1"', "opaque"))
KEYPOINT_X_M = (-0.875, -0.525, -0.175, 0.175, 0.525, 0.875)  # on the slab's face z = 0.1; the last has no veil
RANGE_M = 5.0


def _veiled_target(folder) -> str:
    """A 2 x 1 x 0.2 m slab with six keypoints along its +z face; a 0.3 m square veil 0.3 m in front of each but
    the last."""
    sites = "".join(f'<site name="kp_{k}" pos="{x} 0 0.1"/>' for k, x in enumerate(KEYPOINT_X_M))
    veils = "".join(f'<geom name="veil_{k}" type="box" pos="{KEYPOINT_X_M[k]} 0 0.4" size="0.15 0.15 0.005" '
                    f'{attributes}/>' for k, (attributes, _) in enumerate(VEILS))
    path = folder / "veiled.xml"
    path.write_text('<mujoco model="veiled"><asset><material name="clear" rgba="0.2 0.2 0.2 0.3"/>'
                    '<material name="solid" rgba="0.2 0.2 0.2 1"/></asset><worldbody><body name="target">'
                    '<inertial pos="0 0 0" mass="10" diaginertia="1 1.2 1.4"/>'
                    f'<geom name="slab" type="box" size="1 0.5 0.1" rgba="0.25 0.25 0.25 1"/>{veils}{sites}'
                    '</body></worldbody></mujoco>')
    return str(path)


@pytest.fixture(scope="module")
def veiled(tmp_path_factory):
    """(target file, the view, the keypoints' light share (K,), the labels' visibility (K,)): the slab's +z face
    toward the camera 5 m off, lit from near the camera, 96 px, no shadows."""
    from envisat_pose.datagen.render import SceneRenderer
    from envisat_pose.datagen.render_view import View

    path = _veiled_target(tmp_path_factory.mktemp("veil"))
    R_C_from_T = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])  # +z of T toward the camera
    sun_C = np.array([0.3, -1.0, 0.2]) / np.linalg.norm([0.3, -1.0, 0.2])
    view = View(np.array([0.0, RANGE_M, 0.0]), R_C_from_T, sun_C)
    renderer = SceneRenderer(96, shadows=False, target=path)
    try:
        slab = renderer.model.geom("slab").id
        grey = renderer.render(view)
        renderer.model.geom_rgba[slab][:3] = 0.0
        black = renderer.render(view)
        K = renderer.K
    finally:
        renderer.close()
    uv = grey.corners_K_m @ K.T
    u, v = np.rint(uv[:, :2] / uv[:, 2:]).astype(int).T
    share = grey.gray_u8[v, u].astype(int) - black.gray_u8[v, u].astype(int)
    visible = load_target(path).visible(grey.R_K_from_T, grey.t_K_from_T_m)  # what the factory labels
    return path, view, share, visible


def test_a_keypoint_is_labelled_visible_where_the_image_shows_its_surface(veiled):
    """The light of a keypoint's surface behind each veil against that of the unveiled keypoint: whole (within 2
    grey levels) through every veil MuJoCo draws transparent, none through an opaque one; the label is visible
    exactly where at least half of it arrives (before: every veil hid its keypoint)."""
    _, _, share, visible = veiled
    free = share[-1]
    assert free > 40, share
    for k, (_, drawn_as) in enumerate(VEILS):
        expected = free if drawn_as.startswith("transparent") else 0
        assert abs(share[k] - expected) <= 2, (k, drawn_as, share.tolist())
    np.testing.assert_array_equal(visible, share >= free / 2)
    assert visible.tolist() == [True, True, True, False, False, True]


def test_the_filters_visibility_table_agrees_with_the_labels(veiled):
    """The filter's prediction (filtering.measurements.predicted_visible over the target's table) from the
    view's state gives the labels' visibility, the transparent veils hiding nothing; the target reads the alpha
    MuJoCo draws each geom with."""
    from envisat_pose.filtering.measurements import predicted_visible

    path, view, _, visible = veiled
    target = load_target(path)
    assert [g.alpha for g in target.geoms] == pytest.approx([1.0, 0.3, 0.3, 0.3, 1.0, 1.0])
    x = np.concatenate([view.rho_C_m, np.zeros(3), dcm_to_mrp(view.R_C_from_T.T), np.zeros(3)])
    predicted = predicted_visible(x, target.filter_visibility)
    np.testing.assert_array_equal(predicted, visible)
    assert predicted.tolist() == [True, True, True, False, False, True]
