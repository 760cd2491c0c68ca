"""`envisat estimate --truth RUN.npz` on a truth of a target file with joints: the latched-joint warning names the
file as the truth records it (it once read "--target 'FILE'", a flag the user had not given); `simulate --target`
still names the target it was given."""

import warnings

import pytest

from envisat_pose.app.common import as_flags
from envisat_pose.app.estimate import FLAGS
from envisat_pose.pipelines.campaigns.estimate import truth_target
from envisat_pose.target import load_target

LOOSE = """<mujoco model="loosesat">
  <worldbody>
    <body name="target"><freejoint name="loose"/>
      <geom type="box" size="0.5 0.5 0.5" mass="200"/>
      <site name="kp_a" pos="0.5 0.5 0.5"/><site name="kp_b" pos="-0.5 0.5 0.5"/>
      <site name="kp_c" pos="0.5 -0.5 -0.5"/><site name="kp_d" pos="-0.5 -0.5 0.5"/>
    </body>
  </worldbody>
</mujoco>"""


def _said(load) -> str:
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        load()
    lines = [str(w.message) for w in caught if "latched" in str(w.message)]
    assert len(lines) == 1, lines
    return lines[0]


@pytest.mark.parametrize("folder", ["truth", "given"])
def test_the_latched_joints_warning_names_the_truths_file(tmp_path, folder):
    path = tmp_path / folder / "loose.xml"  # a fresh file each: the load is cached, its warning said once
    path.parent.mkdir()
    path.write_text(LOOSE)
    if folder == "truth":
        said = as_flags(_said(lambda: truth_target({"target": {"file": str(path)}}, "run.npz")), FLAGS)
        assert said.startswith(f"the target file {str(path)!r} of run.npz: 1 joint(s) latched"), said
        assert "--target" not in said
    else:  # a verb's own `target`: the flag it was given
        said = as_flags(_said(lambda: load_target(str(path))), FLAGS)
        assert said.startswith(f"--target {str(path)!r}: 1 joint(s) latched"), said
