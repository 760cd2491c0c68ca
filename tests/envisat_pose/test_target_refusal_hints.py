"""The refusals a first target file meets say what to change, and what they say works.

A box with a dish and a panel as a child body, the whole craft's mass stated on body `target`: the panel's box,
with no mass of its own, weighs its volume at MuJoCo's default density (12 kg) and pulls the centre of mass off
the origin. The refusal said 'move the geoms and sites by its negative', which, done, left it 0.125 m off (the
stated <inertial> stays put). Keypoint sites misspelt (KP_A, kp-B) were refused with 'found 3' alone.
"""

import re
import warnings

import pytest

from envisat_pose.config import ConfigError
from envisat_pose.target import load_target

SAT = """<mujoco model="my_sat">
  <worldbody>
    <body name="target">
      <inertial pos="{inertial}" mass="50" fullinertia="2.0 3.0 2.5 0 0 0"/>
      <geom name="bus" type="box" pos="{bus}" size="0.3 0.3 0.4"/>
      <body name="panel" pos="{panel}">
        <geom name="panel" type="box" pos="0 0.5 0" size="0.01 0.5 0.3"{mass}/>
        <site name="kp_tip_top" pos="0 1.0 0.3"/>
        <site name="kp_tip_bottom" pos="0 1.0 -0.3"/>
      </body>
      <site name="{a}" pos="{kp_a}"/>
      <site name="{b}" pos="{kp_b}"/>
    </body>
  </worldbody>
</mujoco>"""
COM_Y_M = 12 * 0.8 / 62  # the panel's 0.02 x 1 x 0.6 m box at 1000 kg/m^3, 0.8 m out, beside the bus's stated 50 kg


def _sat(tmp_path, name: str, shift_y_m: float = 0.0, mass: str = "", a: str = "kp_A", b: str = "kp_B") -> str:
    """The craft with its bus, its <inertial>, its bus keypoints and its panel moved by shift_y_m along y."""
    at = lambda x, y, z: f"{x} {y + shift_y_m!r} {z}"  # noqa: E731
    path = tmp_path / f"{name}.xml"
    path.write_text(SAT.format(inertial=at(0, 0, 0), bus=at(0, 0, 0), panel=at(0, 0.3, 0), mass=mass, a=a, b=b,
                               kp_a=at(0.3, 0.3, 0.4), kp_b=at(0.3, -0.3, 0.4)))
    return str(path)


def test_the_centre_of_mass_refusal_names_each_bodys_mass_and_both_remedies_load(tmp_path):
    with pytest.raises(ConfigError) as err:
        load_target(_sat(tmp_path, "plain"))
    message = str(err.value)
    assert "'target' 50 kg at [0, 0, 0]; 'panel' 12 kg at [0, 0.8, 0] from its geoms" in message
    assert "give the child bodies' geoms mass='0'" in message
    assert "move its geoms, sites, <inertial> and child bodies by its negative" in message
    # each remedy, done as written, loads: the panel weightless, or everything on body 'target' moved
    assert load_target(_sat(tmp_path, "weightless", mass=' mass="0"')).mass_kg == pytest.approx(50.0)
    moved = load_target(_sat(tmp_path, "moved", shift_y_m=-COM_Y_M))
    assert moved.mass_kg == pytest.approx(62.0)
    assert moved.keypoints_T_m[0] == pytest.approx([0.3, 0.3 - COM_Y_M, 0.4])


def _frame_said(message: str) -> str:
    """The <frame pos='...'> a refusal tells to wrap the geometry in (one, with the offset to use)."""
    found = re.findall(r"<frame pos='[^']*'>", message)
    assert len(found) == 1, message
    return found[0]


def test_the_centre_of_mass_refusal_says_a_frame_moves_the_geometry_and_the_frame_it_says_loads(tmp_path):
    """The refusal names one <frame pos> to wrap the geometry in, with the offset: done as said, the file loads
    (the flat body's geoms off its origin; the craft with a stated <inertial> and a child body, the <inertial>
    moved by hand as the words say)."""
    flat = ('<mujoco><worldbody><body name="target">{}</body></worldbody></mujoco>')
    inner = ('<geom type="box" size="0.5 0.4 0.3" pos="0.2 -0.1 0.05" density="100"/>'
             + "".join(f'<site name="kp_{i}" pos="{x}"/>' for i, x in
                       enumerate(["0.7 0.3 0.35", "-0.3 0.3 0.35", "0.7 -0.5 0.35", "0.7 0.3 -0.25"])))
    path = tmp_path / "flat.xml"
    path.write_text(flat.format(inner))
    with pytest.raises(ConfigError) as err:
        load_target(str(path))
    frame = _frame_said(str(err.value))
    assert frame == "<frame pos='-0.2 0.1 -0.05'>" and "or wrap them in " + frame in str(err.value)
    path.write_text(flat.format(frame + inner + "</frame>"))
    assert load_target(str(path)).keypoints_T_m[0] == pytest.approx([0.5, 0.4, 0.3])
    with pytest.raises(ConfigError) as err:
        load_target(_sat(tmp_path, "plain"))
    frame = _frame_said(str(err.value))
    text = open(_sat(tmp_path, "plain")).read()
    body = text[text.index('<geom name="bus"'):text.rindex("</body>")]  # all but the <inertial>
    assert '<inertial pos="0 0.0 0"' in text
    wrapped = text.replace(body, frame + body + "</frame>\n    ").replace('<inertial pos="0 0.0 0"',
                                                                       f'<inertial pos="0 {-COM_Y_M!r} 0"')
    (tmp_path / "wrapped.xml").write_text(wrapped)
    moved = load_target(str(tmp_path / "wrapped.xml"))
    assert moved.mass_kg == pytest.approx(62.0)
    assert moved.keypoints_T_m[0] == pytest.approx([0.3, 0.3 - COM_Y_M, 0.4], abs=1e-6)


def test_too_few_keypoints_names_the_sites_whose_names_missed_the_prefix(tmp_path):
    with pytest.raises(ConfigError) as err:
        load_target(_sat(tmp_path, "misspelt", mass=' mass="0"', a="KP_A", b="kp-B"))
    message = str(err.value)
    assert "(found 2; not keypoints: its site(s) 'KP_A', 'kp-B', whose names do not start with 'kp_'" in message


BURIED = """<mujoco model="dish_sat">
  <worldbody>
    <body name="target">
      <geom name="bus" type="box" size="0.5 0.5 0.5" mass="100"/>
      <geom name="dish" type="cylinder" pos="0 0 1.5" size="0.7 0.02" mass="0"/>
      <site name="kp_a" pos="0.5 0.5 0.5"/>
      <site name="kp_b" pos="-0.5 0.5 0.5"/>
      <site name="kp_c" pos="0.5 -0.5 -0.5"/>
      <site name="kp_d" pos="-0.5 -0.5 -0.5"/>
      <site name="kp_dish_centre" pos="0 0 1.5"/>
      <site name="kp_dish_edge" pos="0.7 0 1.5"/>
    </body>
  </worldbody>
</mujoco>"""


def test_a_keypoint_no_view_sees_is_warned_of_by_name(tmp_path):
    """A site at the centre of a 4 cm dish (within the 5 cm a keypoint may lie from the surface) is inside the
    solid: no view labelled it visible, the detector never learnt it and calibrate never found it, without a
    word. Its file loads with a warning naming it alone; a file whose keypoints are all seen loads without one."""
    path = tmp_path / "dish_sat.xml"
    path.write_text(BURIED)
    with pytest.warns(UserWarning, match="hidden from each of") as caught:
        load_target(str(path))
    messages = [str(w.message) for w in caught if "hidden from each of" in str(w.message)]
    assert len(messages) == 1 and "'kp_dish_centre'" in messages[0] and "kp_dish_edge" not in messages[0]
    path.write_text(BURIED.replace('<site name="kp_dish_centre" pos="0 0 1.5"/>',
                                   '<site name="kp_dish_centre" pos="0 0 1.52"/>'))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert load_target(str(path)).num_keypoints == 6


def test_a_corner_site_beside_kp_sites_is_warned_of_as_no_keypoint(tmp_path):
    """A craft written from ENVISAT's file keeps one site named 'corner_<name>' among its kp_ sites: a file with
    kp_ sites takes those alone, so the corner site was dropped from the keypoints without a word (12 measured
    where the user wrote 13). It loads with a warning naming that site; its kp_ sites are the keypoints, and a
    file of kp_ sites alone (or ENVISAT's corner_ sites alone) says nothing."""
    path = _sat(tmp_path, "mixed", mass=' mass="0"', b="corner_B")
    with open(path) as f:  # a third bus corner, so that four kp_ sites remain
        text = f.read().replace('<site name="kp_A"', '<site name="kp_C" pos="-0.3 0.3 0.4"/><site name="kp_A"')
    with open(path, "w") as f:
        f.write(text)
    with pytest.warns(UserWarning, match="are not keypoints") as caught:
        target = load_target(path)
    messages = [str(w.message) for w in caught if "are not keypoints" in str(w.message)]
    assert len(messages) == 1 and "'corner_B'" in messages[0] and "'kp_<name>'" in messages[0]
    assert target.keypoint_names == ("C", "A", "tip_top", "tip_bottom")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert load_target(_sat(tmp_path, "plain_kp", mass=' mass="0"')).num_keypoints == 4
        assert load_target().num_keypoints == 8  # ENVISAT: corner_A..H, no kp_ site
