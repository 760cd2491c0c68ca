"""Another target's weights given without --target: every verb's one line tells the user the flag to type,
`--target`, not the library's field name `target` (calibrate and run said "(target; in Python ...)")."""

import os
import sys

import pytest

sys.path.insert(0, os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "perception"))
from keypoint_cases import untrained_weights  # noqa: E402

from envisat_pose.app.cli import main  # noqa: E402

# the repository's models folder, by this file's place: the tests run from any working folder
MODELS = os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))), "models")
UPPER = os.path.join(MODELS, "upper_stage.xml")


@pytest.fixture(scope="module")
def weights(tmp_path_factory):
    return untrained_weights(tmp_path_factory.mktemp("hint") / "upper.safetensors", UPPER, sigma_px=1.5)


@pytest.mark.parametrize("argv", [
    ["calibrate", "--data", "no_such_data", "--out", "{out}/w.safetensors"],
    ["run", "--duration-s", "5", "--out", "{out}"],
    ["detect", "--data", "no_such_data", "--out", "{out}/det.npz"],
    ["evaluate", "--data", "no_such_data", "--json", "{out}/e.json"],
])
def test_target_weights_without_target_name_the_flag(weights, tmp_path, capsys, argv):
    out = tmp_path / "out"
    argv = [a.format(out=out) for a in argv]
    assert main(argv[:1] + ["--weights", weights, *argv[1:], "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "not ENVISAT's" in err[0], err
    assert "(--target;" in err[0], err[0]
    assert not out.exists()
