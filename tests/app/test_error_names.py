"""A library error's leading argument name becomes the verb's flag (app/common.as_flags), and nothing else does:
a path whose first folder is named like an argument (`data/x.safetensors`) and a config field (`data.input_px`)
are printed as they are (they read `--data/x.safetensors` and `--data.input_px`)."""

from envisat_pose.app.cli import main
from envisat_pose.app.common import as_flags


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
