"""The one config resolution of every job: defaults, then the scenario's part, then the file, then the flags."""

from dataclasses import dataclass, field

import pytest

from envisat_pose.config import ConfigError, InputError, check, resolve_job_config


@dataclass(frozen=True)
class Section:
    rate_hz: float = 1.0
    kind: str = "markers3d"


@dataclass(frozen=True)
class Job:
    runs: int = 1
    seed: int = 0
    duration_s: float = 100.0
    section: Section = field(default_factory=Section)

    def validate(self, prefix: str = "") -> None:
        check(self.runs >= 1, f"{prefix + '.' if prefix else ''}runs", self.runs, "at least 1 run")


def test_each_layer_overrides_the_one_before(tmp_path):
    path = tmp_path / "job.toml"
    path.write_text("seed = 5\nruns = 3\n[section]\nrate_hz = 2.0\n")
    scenario = {"duration_s": 600.0, "seed": 1, "section": {"kind": "pixels", "rate_hz": 0.5}}
    cfg = resolve_job_config(Job, scenario, str(path), {"runs": 9, "section.kind": None, "seed": None})
    # duration from the scenario, seed and rate from the file (over the scenario), runs from the flag (over the
    # file), kind from the scenario (the flag was not given), everything else the defaults
    assert cfg == Job(runs=9, seed=5, duration_s=600.0, section=Section(rate_hz=2.0, kind="pixels"))
    assert resolve_job_config(Job, {}, None, {}) == Job()
    assert scenario == {"duration_s": 600.0, "seed": 1, "section": {"kind": "pixels", "rate_hz": 0.5}}  # untouched


def test_complete_fills_values_that_depend_on_others():
    def complete(data):
        return {**data, "seed": 10 * data.get("runs", 1)}

    assert resolve_job_config(Job, {}, None, {"runs": 4}, complete).seed == 40


def test_problems_name_the_field_or_the_file(tmp_path):
    with pytest.raises(ConfigError, match=r"runs = 0: expected at least 1 run"):
        resolve_job_config(Job, {}, None, {"runs": 0})
    with pytest.raises(ConfigError, match=r"section.speed"):
        resolve_job_config(Job, {"section": {"speed": 3}}, None, {})
    with pytest.raises(ConfigError, match=r"sweep.runs = 0"):
        resolve_job_config(Job, {}, None, {"runs": 0}, prefix="sweep")
    with pytest.raises(InputError, match="does not exist"):
        resolve_job_config(Job, {}, str(tmp_path / "missing.toml"), {})
