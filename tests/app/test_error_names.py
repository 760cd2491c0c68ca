"""A library error's leading argument name becomes the verb's flag (app/common.as_flags), and nothing else does:
a path whose first folder is named like an argument (`data/x.safetensors`) and a config field (`data.input_px`)
are printed as they are (they read `--data/x.safetensors` and `--data.input_px`)."""

import os

from envisat_pose.app.cli import main
from envisat_pose.app.common import as_flags

# the repository's models folder, by this file's place: the tests run from any working folder
MODELS = os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))), "models")


def test_only_a_leading_name_becomes_a_flag():
    names = {"src": "--images", "data": "--data", "out_dir": "--out"}
    assert as_flags("src 'a/b': not found", names) == "--images 'a/b': not found"
    assert as_flags("out_dir: expected a folder", names) == "--out: expected a folder"
    assert as_flags("data/x.safetensors: not a readable safetensors file", names) == \
        "data/x.safetensors: not a readable safetensors file"
    assert as_flags("data.input_px = 128: expected a multiple of 32", names) == \
        "data.input_px = 128: expected a multiple of 32"


def test_a_weights_path_under_data_is_named_as_typed(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "data").mkdir()
    (tmp_path / "data" / "x.safetensors").write_bytes(b"not safetensors")
    (tmp_path / "frames").mkdir()
    assert main(["detect", "--weights", "data/x.safetensors", "--data", "frames", "--out", "det"]) == 2
    err = capsys.readouterr().err
    assert "data/x.safetensors" in err and "--data/x.safetensors" not in err, err


def test_bf16_for_another_target_is_named_as_the_flag_the_user_typed(tmp_path, capsys):
    """The library says `bf16` (a Python argument), the command line `--bf16`."""
    from envisat_pose.config import InputError
    from envisat_pose.pipelines.tracking.build import tracker_detector

    try:
        tracker_detector("any.safetensors", target="models/cubesat_3u.xml", bf16=True)
    except InputError as err:
        assert str(err).startswith("bf16: ")
    else:
        raise AssertionError("bf16 with another target's detector was not refused")
    assert main(["run", "--target", "models/upper_stage.xml", "--weights",
                 os.path.join(MODELS, "upper_stage_detector.safetensors"),
                 "--bf16", "--duration-s", "5", "--out", str(tmp_path / "r")]) == 2
    err = capsys.readouterr().err
    assert "--bf16: ENVISAT's corner detector only" in err and not (tmp_path / "r").exists(), err


def test_a_bad_init_error_scale_is_named_as_its_flag_by_estimate_as_by_montecarlo(capsys, tmp_path):
    """estimate named the config field (`init_error_scale = 0.0`), montecarlo the flag."""
    for argv in (["estimate", "--out", str(tmp_path / "e.npz")], ["montecarlo", "--out", str(tmp_path / "mc")]):
        assert main([*argv, "--scenario", "default", "--init-error-scale", "0", "--duration-s", "5"]) == 2
        err = capsys.readouterr().err
        assert ": error: --init-error-scale 0.0: expected a scale" in err, err


def test_a_warning_about_a_value_names_the_flag_where_it_was_typed():
    """A job's warning about a field's value ('workers = 8: ...', pools.warn_oversubscribed) reads as its errors do:
    '--workers 8: ...' where the flag was typed, the field's own name where a config file set it."""
    from envisat_pose.app.flag_rules import warning_text

    names = {"workers": "--workers", "src": "--images"}
    assert warning_text("workers = 8: too many", names, ["run", "--workers", "8"]) == "--workers 8: too many"
    assert warning_text("workers = 8: too many", names, ["run", "--workers=8"]) == "--workers 8: too many"
    assert warning_text("workers = 8: too many", names, ["run", "--config", "r.toml"]) == "workers = 8: too many"
    assert warning_text("src 'a': no frames", names, []) == "--images 'a': no frames"  # others as as_flags
