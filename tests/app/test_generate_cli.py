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


def test_a_sequence_in_the_earths_shadow_is_said_to_be(tmp_path, capsys):
    """The upper stage's slow tumble at seed 101 starts in the shadow with the seed's sun: every frame black but
    for the noise. The warning's count is the labels' own (scene.eclipse); the same sequence lit by a given sun
    warns nothing."""
    from envisat_pose.datagen.dataset import iter_samples
    from envisat_pose.shard_reader import checked_shards

    args = ["generate", "--mode", "sequence", "--target", "models/upper_stage.xml", "--scenario", "slow-tumble",
            "--seed", "101", "--num-images", "3", "--resolution", "48", "--quiet"]
    assert main(args + ["--out", str(tmp_path / "dark")]) == 0
    err = capsys.readouterr().err
    dark = sum(bool(label["scene"]["eclipse"]) for _, label, _ in
               iter_samples(checked_shards(str(tmp_path / "dark"))[0]))
    assert dark == 3 and "warning: 3 of 3 frames are in the Earth's shadow" in err and "set sun_dir" in err, err
    lit = tmp_path / "lit.toml"
    lit.write_text("sun_dir = [0.0, 0.0, 1.0]\n")  # along the orbit normal: never behind the Earth
    assert main(args + ["--config", str(lit), "--out", str(tmp_path / "lit")]) == 0
    assert "shadow" not in capsys.readouterr().err


def test_an_interrupted_resumable_job_says_how_to_go_on(tmp_path, monkeypatch, capsys):
    """Ctrl-C in generate or montecarlo (resumable: the same command finishes what they wrote) says so; a verb
    whose outputs are staged says only that it was interrupted."""
    import envisat_pose.app.generate as generate
    import envisat_pose.app.montecarlo as montecarlo
    import envisat_pose.app.simulate as simulate

    def stop(args):
        raise KeyboardInterrupt

    for module, name in ((generate, "run_generate_cli"), (montecarlo, "run_montecarlo"),
                         (simulate, "run_simulate_cli")):
        monkeypatch.setattr(module, name, stop)
    hint = "run the same command again to finish it"
    assert main(["generate", "--out", str(tmp_path / "g")]) == 130
    assert capsys.readouterr().err.startswith(f"envisat generate: interrupted; {hint}")
    assert main(["montecarlo", "--scenario", "default", "--out", str(tmp_path / "m")]) == 130
    assert capsys.readouterr().err.startswith(f"envisat montecarlo: interrupted; {hint}")
    assert main(["simulate", "--out", str(tmp_path / "r.npz")]) == 130
    assert capsys.readouterr().err.strip() == "envisat simulate: interrupted"


def test_appendages_are_recorded_only_where_the_target_has_them(tmp_path):
    """Random views switch ENVISAT's appendages (geom group 4) on; the CubeSat has none, so its labels say none
    were drawn (they said 'on', and `dataset inspect` counted them)."""
    from envisat_pose.datagen.dataset import dataset_stats, iter_samples
    from envisat_pose.shard_reader import checked_shards

    for target, drawn in (("models/envisat.xml", True), ("models/cubesat_3u.xml", False)):
        out = str(tmp_path / target.split("/")[-1])
        assert main(["generate", "--target", target, "--num-images", "2", "--resolution", "48", "--out", out,
                     "--quiet"]) == 0
        assert [label["scene"]["appendages"] for _, label, _ in iter_samples(checked_shards(out)[0])] == [drawn] * 2
        assert ("appendages" in dataset_stats(out)["corruption_levels"]) == drawn


def test_ctrl_c_while_the_verbs_load_is_one_line(monkeypatch, capsys):
    """The verbs' modules are imported before a verb runs (numpy, scipy): Ctrl-C there printed a traceback."""
    import envisat_pose.app.cli as cli

    def interrupted():
        raise KeyboardInterrupt

    monkeypatch.setattr(cli, "build_parser", interrupted)
    assert main(["generate", "--out", "x"]) == 130
    assert capsys.readouterr().err == "envisat: interrupted\n"


def test_the_written_config_records_the_target_files_sha256_and_a_rerun_refuses_the_file_changed(tmp_path, capsys):
    """generate.config.toml records its target file's sha256 beside it (target_sha256), as the manifest does: a
    rerun from it refuses the file once it changed, in one line naming it and the recorded sha256, with nothing
    written; another --target given over the config's is taken as it is."""
    import shutil
    import tomllib

    from envisat_pose.target import resolve_target_path
    from envisat_pose.target_assets import target_sha256

    target = tmp_path / "stage.xml"
    shutil.copy(resolve_target_path("models/upper_stage.xml"), target)
    first, edited, other = (str(tmp_path / name) for name in ("first", "edited", "other"))
    small = ["--num-images", "2", "--resolution", "48", "--quiet"]
    assert main(["generate", "--target", str(target), *small, "--out", first]) == 0
    written = os.path.join(first, "generate.config.toml")
    recorded = tomllib.loads(open(written).read())["target_sha256"]
    assert recorded == target_sha256(str(target))
    target.write_text(target.read_text() + "<!-- edited since -->\n")
    refused(["generate", "--config", written, "--out", edited], capsys, edited,
            "changed since the config was written", str(target), recorded[:12])
    assert main(["generate", "--config", written, "--target", "models/upper_stage.xml", "--out", other,
                 "--quiet"]) == 0


def test_a_bad_flag_value_is_named_as_the_flag_typed_and_a_config_files_as_its_key(tmp_path, capsys):
    """generate named its config field for a flag the user typed (`num_images = -3`, `resolution_px = 8`), where
    the other jobs name the flag; a config file's value stays named by its key (the flag was not typed)."""
    out = str(tmp_path / "ds")
    for flags, said in ((["--num-images", "-3"], "--num-images -3: expected 1 to 100000000 images"),
                        (["--shard-size", "0"], "--shard-size 0: expected at least 1 image per shard"),
                        (["--resolution", "8"], "--resolution 8: expected a resolution in [16, 4096] px"),
                        (["--mode", "foo"], "--mode 'foo': expected one of"),
                        (["--target", str(tmp_path / "nope.xml")], "--target '"),
                        (["--mode", "sequence", "--scenario", "nope"], "--scenario 'nope'"),
                        # as run_generate's own ConfigError says them (tests/pipelines/test_verb_parity.py)
                        (["--workers", "0"], "--workers 0: expected at least 1 worker process (an integer)"),
                        (["--scheduler", "127.0.0.1:1"], "--scheduler '127.0.0.1:1': expected an address only with "
                                                         "backend 'dask'")):
        refused(["generate", *flags, "--out", out], capsys, out, f"envisat generate: error: {said}")
    (tmp_path / "g.toml").write_text("num_images = 0\n")
    refused(["generate", "--config", str(tmp_path / "g.toml"), "--out", out], capsys, out, "error: num_images = 0: ")
