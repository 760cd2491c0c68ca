"""TrackerConfig in sections: a TOML file's [tracker.<section>] tables build it, each section validates its own
fields under its own dotted name, the written config reads back the same, and a key of the old flat layout is
refused with one line naming its new home. min_corners, renamed min_keypoints (any target's keypoints), is taken one
release under its old name with a warning naming the new one; both names are refused."""

import dataclasses
import os
import subprocess
import sys
import tomllib
import warnings

import pytest

from envisat_pose.config import ConfigError, DeprecatedKeyWarning, MovedKeyError, from_dict, to_dict, to_toml
from envisat_pose.pipelines.tracking.tracker_config import (
    MOVED_KEYS,
    SECTIONS,
    AcquireConfig,
    RoiConfig,
    TrackerConfig,
)


def test_every_moved_key_names_one_field_of_a_section():
    """The hint's table points each old key at a real field, and no two old keys at the same one."""
    cfg = TrackerConfig()
    assert set(SECTIONS) == {f.name for f in dataclasses.fields(TrackerConfig)}
    for old, new in MOVED_KEYS.items():
        section, key = new.split(".")
        assert key in {f.name for f in dataclasses.fields(getattr(cfg, section))}, (old, new)
    assert len(set(MOVED_KEYS.values())) == len(MOVED_KEYS)


def test_sections_are_read_from_toml_tables_and_written_back_the_same():
    text = ("[tracker.acquire]\nframes = 12\n\n[tracker.gate]\nraw = true\n\n"
            "[tracker.noise]\ndetector_q_sigma = [0.0, 0.0, 1e-5, 0.0]\n")
    cfg = from_dict(TrackerConfig, tomllib.loads(text)["tracker"], prefix="tracker")
    assert cfg.acquire.frames == 12 and cfg.gate.raw is True and cfg.noise.detector_q_sigma == (0.0, 0.0, 1e-5, 0.0)
    assert cfg.acquire.min_keypoints == TrackerConfig().acquire.min_keypoints  # the rest at its defaults
    written = tomllib.loads(to_toml({"tracker": to_dict(cfg)}))
    assert "[tracker.acquire]" in to_toml({"tracker": to_dict(cfg)})
    assert from_dict(TrackerConfig, written["tracker"], prefix="tracker") == cfg


@pytest.mark.parametrize("old, value, new", [("gate_raw", True, "tracker.gate.raw"),
                                             ("acquire_frames", 12, "tracker.acquire.frames"),
                                             ("roi", False, "tracker.roi.enabled"),
                                             ("array_cue", False, "tracker.array_cue.enabled")])
def test_a_flat_key_is_refused_with_its_new_home(old, value, new):
    """roi and array_cue were flags and are now sections: their old scalar values are caught too."""
    with pytest.raises(MovedKeyError) as err:
        from_dict(TrackerConfig, {old: value}, prefix="tracker")
    assert str(err.value) == f"tracker.{old}: moved to {new}"


def test_each_section_validates_under_its_own_name():
    with pytest.raises(ConfigError, match=r"tracker\.integrity\.confirm_frames = 30"):
        from_dict(TrackerConfig, {"integrity": {"confirm_frames": 30}}, prefix="tracker")
    with pytest.raises(ConfigError, match=r"tracker\.noise\.correlation_in = 'sideways'"):
        from_dict(TrackerConfig, {"noise": {"correlation_in": "sideways"}}, prefix="tracker")
    with pytest.raises(ConfigError, match=r"^frames = 2"):  # a section built in Python is checked when built
        TrackerConfig(acquire=dataclasses.replace(TrackerConfig().acquire, frames=2))


def _run_config(tmp_path, text: str):
    """The `run` job's config built as the verb builds it (resolve_job, the scenario 'default') from a file."""
    from envisat_pose.pipelines.jobs import resolve_job

    path = tmp_path / "run.toml"
    path.write_text(text)
    return resolve_job("run", "default", str(path))


@pytest.mark.parametrize("section, value", [("acquire", 6), ("roi", 3)])
def test_min_keypoints_sets_the_keypoints_a_frame_needs_without_a_warning(tmp_path, section, value):
    with warnings.catch_warnings():
        warnings.simplefilter("error", DeprecatedKeyWarning)
        cfg = _run_config(tmp_path, f"[tracker.{section}]\nmin_keypoints = {value}\n")
    assert getattr(cfg.tracker, section).min_keypoints == value
    written = to_toml(to_dict(cfg))
    assert f"min_keypoints = {value}" in written and "min_corners" not in written


@pytest.mark.parametrize("section, value", [("acquire", 6), ("roi", 3)])
def test_a_files_min_corners_still_sets_it_one_release_with_a_warning_naming_the_new_key(tmp_path, section, value):
    """A file of the release before: its value taken, one warning naming the new key; the job's written config
    says min_keypoints (a rerun from it warns no more)."""
    with pytest.warns(DeprecatedKeyWarning) as caught:
        cfg = _run_config(tmp_path, f"[tracker.{section}]\nmin_corners = {value}\n")
    assert [str(w.message) for w in caught] == [
        f"tracker.{section}.min_corners is deprecated: use tracker.{section}.min_keypoints"]
    assert getattr(cfg.tracker, section).min_keypoints == value
    assert "min_corners" not in to_toml(to_dict(cfg))


@pytest.mark.parametrize("section", ["acquire", "roi"])
def test_both_names_are_refused_naming_both(tmp_path, section):
    with pytest.raises(ConfigError) as err:
        _run_config(tmp_path, f"[tracker.{section}]\nmin_corners = 5\nmin_keypoints = 6\n")
    assert str(err.value) == (f"tracker.{section}.min_corners = 5: expected tracker.{section}.min_keypoints alone "
                              f"(min_corners is its deprecated name), not both: tracker.{section}.min_keypoints = 6 "
                              "is given too")


@pytest.mark.parametrize("cls", [AcquireConfig, RoiConfig])
def test_a_python_caller_of_min_corners_keeps_working_with_a_warning(cls):
    """The constructor's keyword, a table given as a dict, and an attribute read: each warned, each the same
    field; both keywords refused."""
    name = cls.__name__
    with pytest.warns(DeprecatedKeyWarning, match=rf"^{name}\.min_corners is deprecated: use {name}\.min_keypoints$"):
        built = cls(min_corners=5)
    assert built == cls(min_keypoints=5)
    with pytest.warns(DeprecatedKeyWarning, match=rf"^{name}\.min_corners is deprecated"):
        assert built.min_corners == 5
    section = "acquire" if cls is AcquireConfig else "roi"
    with pytest.warns(DeprecatedKeyWarning, match=rf"^{section}\.min_corners is deprecated: use {section}\.min_keyp"):
        assert getattr(TrackerConfig(**{section: {"min_corners": 5}}), section) == built
    with pytest.raises(ConfigError, match=rf"^{name}\.min_corners = 5: expected {name}\.min_keypoints alone"):
        cls(min_corners=5, min_keypoints=6)


def test_the_verb_prints_the_deprecation_in_a_fresh_interpreter(tmp_path):
    """`envisat run --config OLD.toml` as a user runs it (Python's default warning filters, not the tests'): the
    warning line names the new key (a DeprecationWarning would be hidden there). A rate no camera has stops the
    job after the config is built."""
    cfg = tmp_path / "old.toml"
    cfg.write_text("rate_hz = 1e-300\n\n[tracker.acquire]\nmin_corners = 6\n")
    env = {k: v for k, v in os.environ.items() if k != "PYTHONWARNINGS"}
    proc = subprocess.run([sys.executable, "-m", "envisat_pose.app.cli", "run", "--config", str(cfg), "--out",
                           str(tmp_path / "out")], capture_output=True, text=True, env=env, timeout=120)
    assert proc.returncode == 2 and proc.stderr.splitlines()[0] == (
        "envisat run: warning: tracker.acquire.min_corners is deprecated: use tracker.acquire.min_keypoints"), \
        proc.stderr
