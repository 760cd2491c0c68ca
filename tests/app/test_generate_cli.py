"""`envisat generate` as a user meets it: flags that do not apply to the mode are refused in one line before any
work; a rerun with nothing to do draws no progress bar, only its line."""

import os
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))  # the folder's own helpers
from refusals import refused  # noqa: E402

from envisat_pose.app.cli import main  # noqa: E402


def test_random_mode_refuses_a_scenario(tmp_path, capsys):
    out = str(tmp_path / "ds")
    refused(["generate", "--num-images", "2", "--resolution", "64", "--scenario", "close-25m", "--out", out],
            capsys, out, "--scenario close-25m", "--mode sequence", "random")


def test_a_rerun_with_nothing_to_do_draws_no_bar(tmp_path, capsys):
    args = ["generate", "--num-images", "2", "--shard-size", "2", "--resolution", "64", "--out", str(tmp_path / "ds")]
    assert main(args) == 0
    assert "generate" in capsys.readouterr().err  # the first run's bar
    assert main(args) == 0
    captured = capsys.readouterr()
    assert captured.err == "" and captured.out.startswith("nothing to do: 2 images already there"), captured
    assert os.path.isfile(tmp_path / "ds" / "manifest.json")
