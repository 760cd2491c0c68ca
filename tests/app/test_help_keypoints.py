"""The help of the verbs that take any target (`--target FILE.xml`: its keypoints are kp_ sites) says keypoints;
"corners" only where it names ENVISAT's (its corners A-H, a file's corners_* key)."""

import re

import pytest

from envisat_pose.app.cli import main

ENVISATS = re.compile(r"ENVISAT's corner(s| detector's)|\(ENVISAT's: its corners\)|its corner detector|corners_\w+")


@pytest.mark.parametrize("verb", [["generate"], ["dataset"], ["dataset", "inspect"], ["simulate"], ["estimate"],
                                  ["montecarlo"], ["track"]])
def test_the_help_of_a_verb_for_any_target_says_keypoints(verb, capsys, monkeypatch):
    monkeypatch.setenv("COLUMNS", "1000")  # one line per option: no phrase broken across lines
    with pytest.raises(SystemExit) as done:
        main([*verb, "--help"])
    text = capsys.readouterr().out
    assert done.value.code == 0 and "usage:" in text
    left = [line.strip() for line in ENVISATS.sub("", text).splitlines() if "corner" in line.lower()]
    assert left == [], f"`envisat {' '.join(verb)} --help` says corners for any target: {left}"
