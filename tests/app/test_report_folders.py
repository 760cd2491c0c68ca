"""`envisat report` on the folders a user gives: RMSE / PCRLB shown as `envisat montecarlo` prints it (three
decimals, not three significant digits: 1.103 once read "1.1"), and a folder that is missing, a file or given
twice refused in one line naming it, nothing written. Campaign folders here are written by hand (summary.json
alone): no campaign is run."""

import json
from html.parser import HTMLParser

import pytest

from envisat_pose.app.cli import main

BLOCKS = ("position", "velocity", "attitude", "angular_velocity")
RATIOS = {"position": 1.0166041196, "velocity": 1.0049306224, "attitude": 0.8712204255, "angular_velocity": 1.1034383389}


class Cells(HTMLParser):
    def __init__(self):
        super().__init__()
        self.cells, self._cell = [], None

    def handle_starttag(self, tag, attrs):
        if tag in ("td", "th"):
            self._cell = ""

    def handle_data(self, data):
        if self._cell is not None:
            self._cell += data

    def handle_endtag(self, tag):
        if tag in ("td", "th") and self._cell is not None:
            self.cells.append(self._cell)
            self._cell = None


def _campaign(folder):
    folder.mkdir(parents=True)
    summary = {"scenario": "default", "runs": 4, "n_runs": 4, "steps": 61, "seed": 0, "settle_s": 30.0,
               "n_diverged": 0, "nees_mean": 11.5, "nees_bounds": [11.0, 13.0], "nees_run_bounds": [9.0, 15.0],
               "nis_mean_per_dof": 1.0, "measurement": {"kind": "markers3d", "sigma_m": 0.02, "rate_hz": 1.0},
               "rmse": dict.fromkeys(BLOCKS, 1e-3), "pcrlb_rms": dict.fromkeys(BLOCKS, 1e-3),
               "inside_3sigma_share": dict.fromkeys(BLOCKS, 0.99), "rmse_over_pcrlb": RATIOS}
    (folder / "summary.json").write_text(json.dumps(summary))
    return folder


def _sweep(folder):
    folder.mkdir(parents=True)
    sweep = {"rates_hz": [0.5, 1.0], "rmse": {b: [1e-3, 1e-3] for b in BLOCKS}, "n_diverged": [0, 0],
             "rmse_over_pcrlb": {b: [RATIOS[b], RATIOS[b]] for b in BLOCKS}, "runs": 4, "nees_mean": [11.0, 12.0],
             "converged": [True, True], "lowest_converged_rate_hz": 0.5, "n_nis_alarm_alone": [0, 0]}
    (folder / "sweep.json").write_text(json.dumps(sweep))
    return folder


def _cells(path):
    page = Cells()
    page.feed(path.read_text(encoding="utf-8"))
    return page.cells


def test_ratios_read_as_the_montecarlo_line_prints_them(tmp_path):
    out = tmp_path / "r.html"
    assert main(["report", str(_campaign(tmp_path / "a")), str(_sweep(tmp_path / "sw")), "--out", str(out)]) == 0
    cells = _cells(out)
    for b, v in RATIOS.items():
        i = cells.index(f"RMSE / PCRLB {b}")
        assert cells[i + 1] == f"{v:.3f}", (b, cells[i + 1])
    # the sweep's rows: the same three decimals, one per block after the four RMSE cells
    row = cells[cells.index("0.5"):][:9]
    assert row[5:9] == [f"{RATIOS[b]:.3f}" for b in BLOCKS], row


@pytest.mark.parametrize("case", ["missing", "file", "twice"])
def test_a_folder_missing_a_file_or_given_twice_is_one_line_naming_it(tmp_path, capsys, case):
    a = _campaign(tmp_path / "a")
    other = {"missing": str(tmp_path / "nope"), "file": str(a / "summary.json"), "twice": str(a) + "/"}[case]
    out = tmp_path / "r.html"
    assert main(["report", str(a), other, "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and repr(other) in err[0], err
    assert {"missing": "no such folder", "file": "is a file", "twice": "give it once"}[case] in err[0], err
    assert not out.exists()


def test_an_unfinished_rate_sweep_is_named_as_one_that_has_no_sweep_json(tmp_path, capsys):
    """A rate sweep stopped before its sweep.json: the line says what the folder lacks for either kind of
    folder (it once spoke of summary.json alone, a campaign's) and how to finish it."""
    sweep = tmp_path / "sw"
    _campaign(sweep / "rate-1hz")  # one rate finished, the sweep not
    assert main(["report", str(sweep), "--out", str(tmp_path / "r.html")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "sweep.json" in err[0] and "rerun its command" in err[0], err


def test_a_field_shown_as_n_a_is_named_with_its_file_and_why(tmp_path, capsys):
    """A summary without one block's RMSE (and a null ratio, no timing.json): the cells read n/a with why, the page
    lists each field under the table with its file, and stderr warns once per field (the cells once read a bare
    "n/a"); a complete folder gets neither."""
    a = _campaign(tmp_path / "a")
    summary = json.loads((a / "summary.json").read_text())
    del summary["rmse"]["attitude"]
    summary["rmse_over_pcrlb"] = dict(RATIOS, velocity=None)
    (a / "summary.json").write_text(json.dumps(summary))
    full = _campaign(tmp_path / "full")
    (full / "timing.json").write_text(json.dumps({"block_wall_s_sum": 3.0, "wall_s_this_invocation": 3.0}))
    out = tmp_path / "r.html"
    assert main(["report", str(a), str(full), "--out", str(out)]) == 0
    cells = _cells(out)
    i = cells.index("RMSE attitude (deg)")
    assert cells[i + 1:i + 3] == ["n/a (missing)", f"{1e-3 * 180 / 3.141592653589793:.4g}"], cells[i:i + 3]
    assert cells[cells.index("RMSE / PCRLB velocity") + 1] == "n/a (null)"
    text = out.read_text(encoding="utf-8")
    path = a / "summary.json"
    expected = [f"{path}: rmse.attitude missing (shown as n/a)", f"{path}: rmse_over_pcrlb.velocity null (shown as n/a)",
                f"{a / 'timing.json'}: missing or unreadable (wall time shown as n/a)"]
    for line in expected:
        assert f"<li>a: {line}</li>" in text, line
    assert str(full) not in text.split("Shown as n/a:")[1].split("</ul>")[0]
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"envisat report: warning: {line}" for line in expected], err


def test_campaigns_of_another_target_or_duration_are_said_not_like_for_like(tmp_path, capsys):
    """An upper stage's 200 s campaign beside ENVISAT's 150 s one: the page says, above the table, that they
    differ in target and duration (each column's value named) and the verb warns it, the table has a duration
    row; two campaigns that differ only in their case (sigma) get no such line. The page once showed them side
    by side with the differences only in the raw config row."""
    a, b, c = _campaign(tmp_path / "us"), _campaign(tmp_path / "env"), _campaign(tmp_path / "us-0.2")
    for folder, target, duration, sigma in ((a, "upper_stage", 200.0, 0.02), (b, "envisat", 150.0, 0.02),
                                             (c, "upper_stage", 200.0, 0.2)):
        s = json.loads((folder / "summary.json").read_text())
        s.update(target={"name": target}, duration_s=duration, settle_s=duration / 2)
        s["measurement"]["sigma_m"] = sigma
        (folder / "summary.json").write_text(json.dumps(s))
    out = tmp_path / "r.html"
    assert main(["report", str(a), str(b), "--out", str(out)]) == 0
    text, cells = out.read_text(encoding="utf-8"), _cells(out)
    assert cells[cells.index("duration") + 1:][:2] == ["200 s", "150 s"]
    err = capsys.readouterr().err
    for what, shown in (("target", "us: upper_stage, env: envisat"), ("duration", "us: 200 s, env: 150 s")):
        line = f"not like for like: the campaigns differ in {what} ({shown})"
        assert line in text.split("<table>")[0] and line in err, (what, err)
    assert main(["report", str(a), str(c), "--out", str(out)]) == 0
    assert "not like for like" not in out.read_text(encoding="utf-8") + capsys.readouterr().err


def test_campaigns_of_one_target_name_but_other_files_are_said_not_like_for_like(tmp_path, capsys):
    """A user's craft edited between two campaigns (another inertia, a keypoint moved) keeps its MJCF model name:
    the summaries' sha256s differ, and the page and the verb say so naming each column's sha256; the same file
    twice, or a summary written before the sha256 was recorded, says nothing. The note once compared the names
    alone and put two bodies side by side as one."""
    sha = {"v1": "88ec56358f71" + "0" * 52, "v2": "511a8da4d80a" + "1" * 52, "v1b": "88ec56358f71" + "0" * 52,
           "old": None}
    for name, digest in sha.items():
        folder = _campaign(tmp_path / name)
        s = json.loads((folder / "summary.json").read_text())
        s["target"] = {"name": "client_sat", **({"sha256": digest} if digest else {})}
        (folder / "summary.json").write_text(json.dumps(s))
    out = tmp_path / "r.html"
    assert main(["report", str(tmp_path / "v1"), str(tmp_path / "v2"), "--out", str(out)]) == 0
    line = ("not like for like: the campaigns differ in target (v1: client_sat (sha256 88ec56358f71...), v2: "
            "client_sat (sha256 511a8da4d80a...))")
    assert line in out.read_text(encoding="utf-8").split("<table>")[0] and line in capsys.readouterr().err
    for pair in (("v1", "v1b"), ("v1", "old")):
        assert main(["report", *(str(tmp_path / p) for p in pair), "--out", str(out)]) == 0
        assert "not like for like" not in out.read_text(encoding="utf-8") + capsys.readouterr().err, pair


@pytest.mark.parametrize("case", ["interrupted", "foreign"])
def test_an_interrupted_campaign_and_a_foreign_folder_each_get_their_own_line(tmp_path, capsys, case):
    """A campaign stopped before its summary.json says it is one, how many blocks are done and to rerun its
    command; a folder that is no campaign at all says so, without telling to rerun a command (both once read
    'not a finished `envisat montecarlo` folder (rerun its command to finish it)')."""
    from envisat_pose.pipelines.campaigns.campaign import MANIFEST_FORMAT

    d = tmp_path / case
    d.mkdir()
    if case == "interrupted":
        blocks = [{"index": i, "file": f"blocks/block-{i:04d}.npz"} for i in range(2)]
        (d / "manifest.json").write_text(json.dumps({"format": MANIFEST_FORMAT, "n_blocks": 5, "blocks": blocks}))
    else:
        (d / "notes.txt").write_text("not a campaign")
    assert main(["report", str(d), "--out", str(tmp_path / "r.html")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and repr(str(d)) in err[0], err
    if case == "interrupted":
        assert "interrupted" in err[0] and "2 of 5 blocks done" in err[0] and "rerun its command" in err[0], err
    else:
        assert "not an `envisat montecarlo` folder" in err[0] and "rerun" not in err[0], err
    assert not (tmp_path / "r.html").exists()
