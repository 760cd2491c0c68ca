"""`envisat montecarlo --config FILE.toml` whose file holds a simulate-style [target] table: the campaign's
`target` is an MJCF path, and the refusal said only "expected a string or nothing (omit it)"; it now says where
the table goes (a scenario file given as --scenario FILE.toml, or the MJCF file as --target FILE.xml). A target
value of another wrong kind keeps the plain message, and nothing is made."""

from envisat_pose.app.cli import main


def test_a_target_table_in_a_campaign_config_is_refused_with_where_it_goes(tmp_path, capsys):
    cfg = tmp_path / "mc.toml"
    cfg.write_text('[target]\nfile = "models/envisat.xml"\n')
    out = tmp_path / "mc"
    assert main(["montecarlo", "--scenario", "default", "--config", str(cfg), "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    assert "expected a string or nothing (omit it)" in err, err
    assert "a scenario file, given as `--scenario FILE.toml`" in err and "`--target FILE.xml`" in err, err
    assert not out.exists()


def test_a_target_of_another_kind_keeps_the_plain_message(tmp_path, capsys):
    cfg = tmp_path / "mc.toml"
    cfg.write_text("target = 3\n")
    assert main(["montecarlo", "--scenario", "default", "--config", str(cfg), "--out", str(tmp_path / "mc"),
                 "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "expected a string or nothing (omit it)" in err and "--scenario FILE.toml" not in err, err
