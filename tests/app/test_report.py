"""`envisat report`: one self-contained HTML page that parses, embeds every figure of every campaign as a PNG
data URI, links nothing outside itself and puts several campaigns side by side."""

import base64
import io
import json
import shutil
from html.parser import HTMLParser

import numpy as np
import pytest

from envisat_pose.app.cli import main

FIGURES = ("envelopes.png", "block_norms.png", "nees_nis.png", "rmse_vs_pcrlb.png")


class Collector(HTMLParser):
    """Images, links and table cells of a page."""

    def __init__(self):
        super().__init__()
        self.imgs, self.refs, self.cells, self._cell = [], [], [], None

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        if tag == "img":
            self.imgs.append(a)
        for key in ("href", "src"):
            if key in a and tag != "img":
                self.refs.append(a[key])
        if tag in ("td", "th"):
            self._cell = ""

    def handle_data(self, data):
        if self._cell is not None:
            self._cell += data

    def handle_endtag(self, tag):
        if tag in ("td", "th") and self._cell is not None:
            self.cells.append(self._cell)
            self._cell = None


@pytest.fixture(scope="module")
def two_campaigns(tmp_path_factory):
    root = tmp_path_factory.mktemp("rep")
    args = ["montecarlo", "--scenario", "default", "--runs", "6", "--duration-s", "120", "--settle-s", "60", "--quiet"]
    assert main(args + ["--out", str(root / "sigma-0.02")]) == 0
    assert main(args + ["--sigma-m", "0.2", "--out", str(root / "sigma-0.2")]) == 0
    return root / "sigma-0.02", root / "sigma-0.2"


def test_report_embeds_every_figure_and_parses(two_campaigns, tmp_path, capsys):
    out = tmp_path / "report.html"
    assert main(["report", *map(str, two_campaigns), "--out", str(out)]) == 0
    text = out.read_text(encoding="utf-8")
    page = Collector()
    page.feed(text)
    page.close()
    assert len(page.imgs) == 2 * len(FIGURES)
    alts = [img["alt"] for img in page.imgs]
    assert sorted(alts) == sorted(FIGURES * 2)
    from PIL import Image

    for img, d, name in zip(page.imgs, [two_campaigns[0]] * 4 + [two_campaigns[1]] * 4, alts):
        prefix = "data:image/png;base64,"
        assert img["src"].startswith(prefix)
        raw = base64.b64decode(img["src"][len(prefix):])
        assert raw == (d / name).read_bytes()  # the campaign's own figure, embedded whole
        assert np.asarray(Image.open(io.BytesIO(raw))).size > 0
    assert page.refs == []  # no stylesheet, script or link to anything outside the page
    assert "http://" not in text.replace("data:", "") or all("http" not in r for r in page.refs)
    # the table: one column per campaign, the numbers of each summary
    assert "sigma-0.02" in page.cells and "sigma-0.2" in page.cells
    for d in two_campaigns:
        s = json.loads((d / "summary.json").read_text())
        assert f"{s['rmse']['position'] * 100:.4g}" in page.cells
        assert f"{s['rmse_over_pcrlb']['attitude']:.3f}" in page.cells  # as the montecarlo line prints it
    assert any(c.startswith("RMSE / PCRLB") for c in page.cells) and any("NEES" in c for c in page.cells)
    assert any("wall" in c for c in page.cells)
    # what sets the campaigns apart is named in the table
    assert "measurement.sigma_m = 0.02" in page.cells and "measurement.sigma_m = 0.2" in page.cells


def test_report_on_a_folder_without_summary_is_one_error_line(two_campaigns, tmp_path, capsys):
    d = tmp_path / "half"
    shutil.copytree(two_campaigns[0], d)
    (d / "summary.json").unlink()
    assert main(["report", str(d), "--out", str(tmp_path / "r.html")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "summary.json" in err[0]
    assert not (tmp_path / "r.html").exists()


@pytest.mark.parametrize("name, text", [
    ("summary.json", "{}"), ("summary.json", "[1, 2]"), ("summary.json", '{"rmse": "oops"}'),
    ("sweep.json", '{"rates_hz": 5}'),
])
def test_a_summary_of_another_shape_is_one_error_line(two_campaigns, tmp_path, capsys, name, text):
    """Valid JSON that is not a summary this report reads (a field missing, a list, a string for a table):
    one line naming the file (once a 23-line traceback), nothing written."""
    d = tmp_path / "odd"
    shutil.copytree(two_campaigns[0], d)
    (d / name).write_text(text)
    assert main(["report", str(d), "--out", str(tmp_path / "r.html")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"{name}: not" in err[0] and "Traceback" not in err[0], err
    assert not (tmp_path / "r.html").exists()


def test_columns_are_named_by_the_shortest_path_that_tells_them_apart():
    from envisat_pose.pipelines.campaigns.report import column_names

    assert column_names(["mc/ref", "tg/upper_stage/mc", "tg/cubesat_3u/mc"]) == ["ref", "upper_stage/mc",
                                                                               "cubesat_3u/mc"]


def test_report_names_each_campaigns_target(two_campaigns, tmp_path):
    """Another spacecraft's campaign (`montecarlo --target`) side by side with ENVISAT's: the table names each
    campaign's target (the name its summary.json records)."""
    other = tmp_path / "upper"
    assert main(["montecarlo", "--scenario", "default", "--target", "models/upper_stage.xml", "--runs", "3",
                 "--duration-s", "60", "--settle-s", "30", "--quiet", "--out", str(other)]) == 0
    out = tmp_path / "report.html"
    assert main(["report", str(two_campaigns[0]), str(other), "--out", str(out)]) == 0
    page = Collector()
    page.feed(out.read_text(encoding="utf-8"))
    assert "target" in page.cells and "envisat" in page.cells and "upper_stage" in page.cells


def test_report_names_the_target_a_scenario_file_gives(tmp_path):
    """A campaign of the user's own scenario file whose [target] names the upper stage (no `target` in the
    campaign's config): the table names the upper stage, as its summary.json and figures do (it once read
    "envisat.xml", the default file, from the config's unset target)."""
    scenario = tmp_path / "my_stage.toml"
    scenario.write_text('description = "upper stage hold"\nbase = "default"\n\n'
                        '[target]\nfile = "models/upper_stage.xml"\n')
    d = tmp_path / "mystage"
    assert main(["montecarlo", "--scenario", str(scenario), "--runs", "2", "--duration-s", "60", "--settle-s", "30",
                 "--quiet", "--out", str(d)]) == 0
    assert json.loads((d / "summary.json").read_text())["target"]["name"] == "upper_stage"
    out = tmp_path / "report.html"
    assert main(["report", str(d), "--out", str(out)]) == 0
    page = Collector()
    page.feed(out.read_text(encoding="utf-8"))
    row = page.cells[page.cells.index("target") + 1]
    assert row == "upper_stage", row


def test_the_diverged_row_and_line_name_the_nis_monitors_lone_alarms(two_campaigns):
    """A summary whose diverged runs include ones the NIS monitor flagged alone says so, in the report's row and
    in `envisat montecarlo`'s line; without any, both read as before."""
    from envisat_pose.app.montecarlo import summary_line
    from envisat_pose.pipelines.campaigns.report import campaign_rows, load_campaign

    c = load_campaign(str(two_campaigns[0]))
    for alone, note in (([], None), ([3], "1 flagged by the filter alone")):
        s = dict(c["summary"], n_diverged=2, diverged_runs=[3, 7], nis_alarm_alone_runs=alone)
        row = dict(campaign_rows(dict(c, summary=s)))["diverged runs"]
        line = summary_line(s)
        assert row.startswith("2 / ") and line.endswith(f"diverged 2/{s['n_runs']}" + (f" ({note})" if note else ""))
        assert (note in row) if note else ("NIS" not in row)


def test_the_nees_band_a_consistent_campaign_lies_within_comes_first(two_campaigns):
    """The line and the report give the band with one sample a run first (a consistent campaign's mean NEES lies
    within it) and the narrower band of independent steps second, named as such; a summary written before the
    run band existed gives its one band, named as the independent steps' (not as the band a consistent campaign
    lies within)."""
    from envisat_pose.app.montecarlo import summary_line
    from envisat_pose.pipelines.campaigns.report import campaign_rows, load_campaign

    c = load_campaign(str(two_campaigns[0]))
    s = dict(c["summary"], nees_mean=10.38, nees_bounds=[11.06, 12.98], nees_run_bounds=[10.21, 13.92])
    line = summary_line(s)
    assert "mean NEES 10.38 (95 % band 10.21..13.92 with one sample a run; 11.06..12.98 if every step were " \
           "independent)" in line
    row = dict(campaign_rows(dict(c, summary=s)))["mean NEES (12 dof)"]
    assert row.index("10.21") < row.index("11.06") and "one sample a run" in row
    older = {k: v for k, v in s.items() if k != "nees_run_bounds"}  # its one band is the independent steps'
    assert "(95 % band 11.06..12.98 if every step were independent)" in summary_line(older)
    row = dict(campaign_rows(dict(c, summary=older)))["mean NEES (12 dof)"]
    assert "11.06 .. 12.98 if every step were independent" in row, row
