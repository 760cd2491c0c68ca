"""A rate sweep's written config (`envisat montecarlo --rates-hz`, its folder's montecarlo.config.toml): the source
line, its [sweep] table and the target file's sha256, which `envisat montecarlo --config` reads back to the same
sweep (it refused the [sweep] table, so a sweep could not be rerun from what it wrote); each rate's campaign
writes its config under another name (rate.config.toml: given alone it would not rerun that campaign)."""

import os
import shutil
import sys
import tomllib

import pytest

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))  # the folder's own helpers
from refusals import refused  # noqa: E402

from envisat_pose.app.cli import main  # noqa: E402

SWEEP = ["montecarlo", "--scenario", "default", "--runs", "2", "--duration-s", "20", "--settle-s", "10",
         "--rates-hz", "1", "0.5", "--seed", "4", "--quiet"]
SAME = ("sweep.json", "montecarlo.config.toml", "rate-1hz/summary.json", "rate-0.5hz/summary.json",
        "rate-1hz/rate.config.toml", "rate-0.5hz/rate.config.toml")


@pytest.fixture(scope="module")
def sweep(tmp_path_factory):
    """A sweep of a target file (the smallest shipped one: the quickest visibility table)."""
    from envisat_pose.target import resolve_target_path

    d = tmp_path_factory.mktemp("sweep")
    target = d / "cube.xml"
    shutil.copy(resolve_target_path("models/cubesat_3u.xml"), target)
    assert main(SWEEP + ["--target", str(target), "--out", str(d / "first")]) == 0
    return d / "first", target


def test_the_written_config_reruns_the_same_sweep(sweep, tmp_path):
    from envisat_pose.pipelines.campaigns.report import load_campaign
    from envisat_pose.provenance import source_line
    from envisat_pose.target_assets import target_sha256

    first, target = sweep
    text = (first / "montecarlo.config.toml").read_text()
    lines = text.splitlines()
    assert lines[0].startswith("# envisat montecarlo: the full validated config of this rate sweep")
    assert lines[1] + "\n" == source_line()
    written = tomllib.loads(text)
    assert written["sweep"]["rates_hz"] == [1.0, 0.5] and written["target_sha256"] == target_sha256(str(target))
    second = tmp_path / "second"
    assert main(["montecarlo", "--config", str(first / "montecarlo.config.toml"), "--out", str(second),
                 "--quiet"]) == 0
    assert sorted(os.listdir(second)) == sorted(os.listdir(first))
    for name in SAME:
        assert (second / name).read_bytes() == (first / name).read_bytes(), name
    for rate in ("rate-1hz", "rate-0.5hz"):  # no config named as montecarlo's that reruns one rate of a sweep
        assert not (first / rate / "montecarlo.config.toml").exists()
        own = (first / rate / "rate.config.toml").read_text()
        assert "`--config ../montecarlo.config.toml` reruns the sweep" in own.splitlines()[0]
        assert load_campaign(str(first / rate))["config"] == own  # `envisat report` on a rate's folder shows it


def test_a_rerun_from_the_written_config_refuses_the_target_file_changed(sweep, tmp_path, capsys):
    """The sweep's config names its target file with its sha256: a rerun from it refuses the file once it changed,
    in one line naming it, writing nothing."""
    first, target = sweep
    copy = tmp_path / "cube.xml"
    shutil.copy(target, copy)
    config = tmp_path / "montecarlo.config.toml"
    config.write_text((first / "montecarlo.config.toml").read_text().replace(str(target), str(copy)))
    recorded = tomllib.loads(config.read_text())["target_sha256"]
    copy.write_text(copy.read_text() + "<!-- edited since -->\n")
    refused(["montecarlo", "--config", str(config), "--out", str(tmp_path / "edited"), "--quiet"], capsys,
            tmp_path / "edited", "changed since the config was written", str(copy), recorded[:12])
