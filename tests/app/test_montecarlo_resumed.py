"""A resumed `envisat montecarlo` campaign (a rerun on a folder that keeps some finished blocks and runs the
rest) did not say so: its 'wrote' line read as a fresh campaign's, and its wall time as the whole campaign's. It
now says how many blocks it kept and how many it ran; a fresh campaign's line says nothing of resuming."""

import pytest

from envisat_pose.app.cli import main
from envisat_pose.pipelines.campaigns.lines import resume_note

ARGS = ["montecarlo", "--scenario", "default", "--runs", "4", "--duration-s", "20", "--block-runs", "2", "--quiet"]


def wrote_line(out: str) -> str:
    return next(line for line in out.splitlines() if line.startswith("wrote "))


@pytest.mark.slow  # ~35 s on 2 cores: three tiny campaigns, each simulating its truth and drawing its figures
def test_a_rerun_says_how_many_blocks_it_kept_and_a_fresh_campaign_says_nothing(tmp_path, capsys):
    out = tmp_path / "mc"
    assert main(ARGS + ["--out", str(out)]) == 0
    assert "resumed" not in capsys.readouterr().out
    (out / "blocks" / "block-0001.npz").unlink()  # as if stopped before its second block finished
    assert main(ARGS + ["--out", str(out)]) == 0
    assert "; resumed: 1 of 2 blocks kept, 1 run now)" in wrote_line(capsys.readouterr().out)
    assert main(ARGS + ["--out", str(out)]) == 0  # a finished campaign rerun: every block kept
    assert "; resumed: 2 of 2 blocks kept, 0 run now)" in wrote_line(capsys.readouterr().out)


def test_the_note_is_empty_without_a_kept_block():
    assert resume_note(10, {"blocks_run_now": 10}) == ""
    assert resume_note(10, None) == "" and resume_note(10, {}) == ""
    assert resume_note(10, {"blocks_run_now": 8}) == "; resumed: 2 of 10 blocks kept, 8 run now"
