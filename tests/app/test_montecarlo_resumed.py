"""A resumed `envisat montecarlo` campaign (a rerun on a folder that keeps some finished blocks and runs the
rest) did not say so: its 'wrote' line read as a fresh campaign's, and its wall time as the whole campaign's. It
now says how many blocks it kept and how many it ran; a fresh campaign's line says nothing of resuming.
A rate sweep's rerun says it over its rates, each rate's count named."""

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


SWEEP = ["montecarlo", "--scenario", "default", "--runs", "2", "--duration-s", "20", "--settle-s", "10",
         "--block-runs", "1", "--rates-hz", "1", "0.5", "--quiet"]


@pytest.mark.slow  # ~50 s on 2 cores: a two-rate sweep of tiny campaigns run twice
def test_a_rerun_sweep_says_per_rate_how_many_blocks_it_kept(tmp_path, capsys):
    """A rate sweep stopped part way and rerun said nothing of the blocks it kept, where a campaign's rerun does."""
    out = tmp_path / "sweep"
    assert main(SWEEP + ["--out", str(out)]) == 0
    assert "resumed" not in wrote_line(capsys.readouterr().out)
    (out / "rate-0.5hz" / "blocks" / "block-0001.npz").unlink()  # as if stopped in the slower rate's last block
    assert main(SWEEP + ["--out", str(out)]) == 0
    assert "; resumed: 3 of 4 blocks kept (0.5 Hz 1 of 2, 1 Hz 2 of 2), 1 run now)" in wrote_line(
        capsys.readouterr().out)


def test_the_sweeps_note_sums_its_rates_and_is_empty_for_a_fresh_sweep():
    from envisat_pose.pipelines.campaigns.lines import sweep_resume_note

    fresh = [{"blocks_run_now": 4}, {"blocks_run_now": 4}]
    assert sweep_resume_note([0.5, 1.0], 4, fresh) == ""
    assert sweep_resume_note([0.5, 1.0], 4, [{"blocks_run_now": 4}, None]) == ""  # a rate's timing unreadable
    assert sweep_resume_note([0.5, 1.0], 4, [{"blocks_run_now": 4}, {"blocks_run_now": 0}]) == (
        "; resumed: 4 of 8 blocks kept (0.5 Hz 0 of 4, 1 Hz 4 of 4), 4 run now")
