"""TrackerConfig in sections: a TOML file's [tracker.<section>] tables build it, each section validates its own
fields under its own dotted name, the written config reads back the same, and a key of the old flat layout is
refused with one line naming its new home."""

import dataclasses
import tomllib

import pytest

from envisat_pose.config import ConfigError, MovedKeyError, from_dict, to_dict, to_toml
from envisat_pose.pipelines.tracking.tracker_config import MOVED_KEYS, SECTIONS, TrackerConfig


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
    assert cfg.acquire.min_corners == TrackerConfig().acquire.min_corners  # the rest at its defaults
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
