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


def _other_target_dataset(folder) -> str:
    """A dataset folder whose manifest records another target's file (no shards: the target is checked first)."""
    import json

    folder.mkdir()
    (folder / "manifest.json").write_text(json.dumps({
        "shards": [], "complete": True, "config": {"target": "my_sat.xml"},
        "target": {"name": "my_sat", "keypoint_names": ["a", "b", "c", "d"]}}))
    return str(folder)


@pytest.mark.parametrize("argv, way", [
    (["evaluate", "--json", "{out}/e.json"], "give its file, `--target my_sat.xml`"),
    (["calibrate", "--out", "{out}/w.safetensors"], "give its file, `--target my_sat.xml`"),
    (["detect", "--out", "{out}/det.npz"], "give its file, `--target my_sat.xml`"),
    (["train", "--out", "{out}", "--steps", "1"], "without --data: `envisat train --target my_sat.xml --out"),
])
def test_another_targets_dataset_without_target_names_the_way_that_works(tmp_path, capsys, argv, way):
    """evaluate and calibrate of a user's own target's dataset said its images 'come from `envisat generate
    --target`' (they did); train said '--target FILE.xml', which with --data is refused: each names what works."""
    data, out = _other_target_dataset(tmp_path / "data"), tmp_path / "out"
    argv = [a.format(out=out) for a in argv]
    assert main(argv[:1] + ["--data", data, *argv[1:], "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and way in err[0], err
    assert "come from `envisat generate" not in err[0] and not out.exists()
