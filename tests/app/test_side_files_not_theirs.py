"""`simulate` and `estimate` write X.config.toml beside --out X.npz, and X.png with --plot (removing it without, as
an earlier run's stale plot): a user's file of either name (no '# envisat JOB:' first line, no PNG mark of the
job: envisat_pose/png_marks.py) was replaced or removed. Now a user's config, or a user's PNG where a plot is
written, is refused in one line naming it; a user's PNG without --plot is left alone, said in a warning; the job's
own earlier files are still replaced and its stale plot removed."""

import os

import pytest

from envisat_pose.app.cli import main
from envisat_pose.png_marks import marked_png, png_job

MINE = b"\x89PNG\r\n\x1a\n the user's own picture"


@pytest.fixture(scope="module")
def truth(tmp_path_factory) -> str:
    path = tmp_path_factory.mktemp("truth") / "truth.npz"
    assert main(["simulate", "--duration-s", "5", "--out", str(path), "--quiet"]) == 0
    return str(path)


def verb(name: str, truth: str) -> list[str]:
    return ["simulate", "--duration-s", "5"] if name == "simulate" else ["estimate", "--truth", truth]


@pytest.mark.parametrize("name", ["simulate", "estimate"])
def test_a_users_png_beside_the_output_is_left_alone_without_plot(name, truth, tmp_path, capsys):
    (tmp_path / "x.png").write_bytes(MINE)
    assert main(verb(name, truth) + ["--out", str(tmp_path / "x.npz"), "--quiet"]) == 0
    assert (tmp_path / "x.png").read_bytes() == MINE
    assert f"warning: left {str(tmp_path / 'x.png')!r} alone" in capsys.readouterr().err


@pytest.mark.parametrize("name", ["simulate", "estimate"])
@pytest.mark.parametrize("side, flags", [("x.png", ["--plot"]), ("x.config.toml", [])])
def test_a_users_side_file_the_job_would_replace_is_refused_in_one_line(name, side, flags, truth, tmp_path, capsys):
    (tmp_path / side).write_bytes(MINE)
    assert main(verb(name, truth) + ["--out", str(tmp_path / "x.npz"), "--quiet"] + flags) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and f"{str(tmp_path / side)!r}" in err and "not the job's to replace" in err, err
    assert os.listdir(tmp_path) == [side] and (tmp_path / side).read_bytes() == MINE


@pytest.mark.parametrize("name", ["simulate", "estimate"])
def test_the_jobs_own_plot_and_config_are_replaced_and_its_stale_plot_removed(name, truth, tmp_path, capsys):
    out = ["--out", str(tmp_path / "x.npz"), "--quiet"]
    assert main(verb(name, truth) + out + ["--plot"]) == 0
    assert png_job(str(tmp_path / "x.png")) == name
    assert main(verb(name, truth) + out + ["--plot"]) == 0
    assert main(verb(name, truth) + out) == 0
    assert sorted(os.listdir(tmp_path)) == ["x.config.toml", "x.npz"]
    assert "warning" not in capsys.readouterr().err


@pytest.mark.parametrize("name", ["simulate", "estimate"])
def test_an_unmarked_plot_beside_the_jobs_own_config_is_its_earlier_plot(name, truth, tmp_path, capsys):
    """A plot written before the mark existed carries none; beside the job's own config it is still the job's."""
    out = ["--out", str(tmp_path / "x.npz"), "--quiet"]
    assert main(verb(name, truth) + out) == 0  # the job's own x.config.toml
    (tmp_path / "x.png").write_bytes(MINE)  # an unmarked plot of that output, as an earlier version wrote it
    assert main(verb(name, truth) + out + ["--plot"]) == 0
    assert png_job(str(tmp_path / "x.png")) == name
    assert main(verb(name, truth) + out) == 0
    assert sorted(os.listdir(tmp_path)) == ["x.config.toml", "x.npz"]
    assert "warning" not in capsys.readouterr().err


def test_a_mark_is_read_back_and_a_plain_png_has_none(tmp_path):
    import cv2
    import numpy as np

    ok, data = cv2.imencode(".png", np.zeros((4, 4, 3), np.uint8))
    (tmp_path / "plain.png").write_bytes(data.tobytes())
    (tmp_path / "marked.png").write_bytes(marked_png(data.tobytes(), "dataset inspect"))
    assert png_job(str(tmp_path / "plain.png")) is None and png_job(str(tmp_path / "missing.png")) is None
    assert png_job(str(tmp_path / "marked.png")) == "dataset inspect"
    assert cv2.imread(str(tmp_path / "marked.png")).shape == (4, 4, 3)  # still a PNG any reader decodes
