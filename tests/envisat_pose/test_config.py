"""A config is validated when built (config.Config), and the layers of a config: defaults, then the scenario's
part, then the file, then the flags."""

import dataclasses
from dataclasses import dataclass, field

import pytest

from envisat_pose.config import Config, ConfigError, InputError, check, from_dict, resolve_job_config


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


@dataclass(frozen=True)
class Rates(Config):
    rate_hz: float = 1.0

    def validate(self, prefix: str = "") -> None:
        check(self.rate_hz > 0, f"{prefix + '.' if prefix else ''}rate_hz", self.rate_hz, "a positive rate")


@dataclass(frozen=True)
class Filled(Config):
    """A config that fills a field left None before it is validated (as the job configs fill their scenario's)."""

    runs: int = 1
    workers: int | None = None
    rates: Rates = field(default_factory=Rates)

    def __post_init__(self) -> None:
        if self.workers is None:
            object.__setattr__(self, "workers", 2 * self.runs)
        super().__post_init__()

    def validate(self, prefix: str = "") -> None:
        p = f"{prefix}." if prefix else ""
        check(self.runs >= 1, f"{p}runs", self.runs, "at least 1 run")
        check(self.workers <= 8, f"{p}workers", self.workers, "at most 8 workers")


def test_a_config_is_validated_when_built():
    """The constructor, dataclasses.replace and from_dict all validate a Config, after its own filling; from_dict
    names a nested table's field under the table, and a table nested deeper under both."""
    assert Filled(runs=3).workers == 6
    with pytest.raises(ConfigError, match=r"^runs = 0: expected at least 1 run"):
        Filled(runs=0)
    with pytest.raises(ConfigError, match=r"^workers = 10"):  # filled from runs, then validated
        Filled(runs=5)
    with pytest.raises(ConfigError, match=r"^rate_hz = -1"):
        dataclasses.replace(Rates(), rate_hz=-1.0)
    with pytest.raises(ConfigError, match=r"^rates\.rate_hz = -1"):
        from_dict(Filled, {"rates": {"rate_hz": -1.0}})
    with pytest.raises(ConfigError, match=r"^sweep\.workers = 10"):
        from_dict(Filled, {"runs": 5}, prefix="sweep")
    with pytest.raises(ConfigError, match=r"^sweep\.rates\.rate_hz = 0"):
        from_dict(Filled, {"rates": {"rate_hz": 0}}, prefix="sweep")
    assert from_dict(Filled, {"runs": 2, "rates": {"rate_hz": 3}}) == Filled(runs=2, rates=Rates(3.0))


def test_a_list_field_given_a_scalar_says_what_its_items_are():
    """A tuple field given one value names the items it takes (adc_bits = "twelve" said 'a list of some
    numbers' of a field of integers)."""
    @dataclass(frozen=True)
    class Lists:
        bits: tuple[int, ...] = (8,)
        scales: tuple[float, ...] = (1.0,)
        axis: tuple[float, float, float] = (0.0, 0.0, 1.0)
        names: tuple[str, ...] = ("a",)
        mixed: tuple[str, float] = ("a", 1.0)

    for name, value, words in (("bits", "twelve", "a list of integers"), ("scales", 2.0, "a list of numbers"),
                               ("axis", 1.0, "a list of 3 numbers"), ("names", "a", "a list of strings"),
                               ("mixed", 1, "a list of 2 values")):
        with pytest.raises(ConfigError, match=f"^{name} = .*: expected {words}$"):
            from_dict(Lists, {name: value})
    with pytest.raises(ConfigError, match=r"^axis = \[1, 2\]: expected a list of 3 values$"):
        from_dict(Lists, {"axis": [1, 2]})  # a list of another length: as before


def test_a_constructor_checks_its_fields_types_as_from_dict_does():
    """Plain Python arguments of the wrong type are one ConfigError naming the field (once a comparison's
    TypeError, or a float of steps that trained one step more), and what from_dict makes is made here too: a
    path as its string, a table given as a dict as its config, numpy's scalars and arrays as Python's."""
    import pathlib

    import numpy as np

    from envisat_pose.config import ConfigError, from_dict, to_dict
    from envisat_pose.filtering.montecarlo import MeasurementConfig
    from envisat_pose.perception.train import TrainConfig
    from envisat_pose.pipelines.campaigns.campaign import MonteCarloConfig
    from envisat_pose.pipelines.campaigns.estimate import EstimateConfig
    from envisat_pose.pipelines.runs.run_config import RunConfig
    from envisat_pose.pipelines.runs.track import TrackConfig

    for build, needle in ((lambda: TrackConfig(rate_hz="1"), "rate_hz = '1': expected a number"),
                          (lambda: TrackConfig(rate_hz=None), "rate_hz = None"),
                          (lambda: TrackConfig(bf16="yes"), "bf16 = 'yes': expected true or false"),
                          (lambda: RunConfig(runs=2.5), "runs = 2.5: expected an integer"),
                          (lambda: RunConfig(image=None), "image = None"),
                          (lambda: TrainConfig(steps=2.5), "steps = 2.5: expected an integer"),
                          (lambda: EstimateConfig(seed="x"), "seed = 'x'")):
        with pytest.raises(ConfigError, match=needle):
            build()
    est = EstimateConfig(measurement={"kind": "pixels"}, runs=np.int64(3))
    assert isinstance(est.measurement, MeasurementConfig) and est.measurement.kind == "pixels"
    assert type(est.runs) is int and hash(est) and from_dict(EstimateConfig, to_dict(est)) == est
    mc = MonteCarloConfig(target=pathlib.Path("models/upper_stage.xml"), duration_s=60.0, runs=2)
    assert mc.target == "models/upper_stage.xml" and to_dict(mc)["target"] == "models/upper_stage.xml"
    m = MeasurementConfig(outages_s=[[1.0, 2.0]], sigma_m=np.float32(0.5))
    assert m.outages_s == ((1.0, 2.0),) and type(m.sigma_m) is float and hash(m)


def test_an_infinite_campaign_duration_is_one_config_error_naming_it():
    """MonteCarloConfig(duration_s=math.inf) (a constructor takes inf where a file's from_dict does not) was a raw
    OverflowError from its filter-step count, not the ConfigError naming duration_s that every other bad value is."""
    import math

    from envisat_pose.pipelines.campaigns.campaign import MonteCarloConfig

    for bad in (math.inf, -math.inf):
        with pytest.raises(ConfigError, match=r"^duration_s = -?inf: expected a finite number"):
            MonteCarloConfig(duration_s=bad, runs=2)
    with pytest.raises(ConfigError, match=r"^duration_s = nan: expected a number \(not NaN\)"):
        MonteCarloConfig(duration_s=math.nan, runs=2)


def test_nan_in_any_configs_number_is_one_config_error_naming_it():
    """A constructor took NaN where a file's from_dict refuses it (an orbit's RAAN, a track's rate, a sigma): the
    field's checks (x > 0, lo <= x <= hi) are all False for NaN only where written so, and several were not."""
    import math

    from envisat_pose.datagen.generate_config import GenerateConfig
    from envisat_pose.datagen.scenario import OrbitConfig
    from envisat_pose.filtering.montecarlo import MeasurementConfig
    from envisat_pose.pipelines.runs.track import TrackConfig

    for build, name in ((lambda: OrbitConfig(raan_deg=math.nan), "raan_deg"),
                         (lambda: MeasurementConfig(sigma_m=math.nan), "sigma_m"),
                         (lambda: TrackConfig(scenario="default", rate_hz=math.nan), "rate_hz"),
                         (lambda: GenerateConfig(sun_dir=(math.nan, 0.0, 1.0)), "sun_dir")):  # (refused before)
        with pytest.raises(ConfigError, match=rf"^{name} = .*nan.*: expected a (number|non-zero)"):
            build()


def test_numpy_nan_in_a_configs_number_is_one_config_error_naming_it():
    """NaN as numpy gives it (np.float64, an array for a tuple field) is refused as Python's float NaN is (the
    constructor converted it to a float and took it: an orbit's RAAN of nan)."""
    import math

    import numpy as np

    from envisat_pose.datagen.scenario import OrbitConfig
    from envisat_pose.pipelines.runs.track import TrackConfig

    for build, name in ((lambda: OrbitConfig(raan_deg=np.float64(math.nan)), "raan_deg"),
                        (lambda: OrbitConfig(i_deg=np.float32(math.nan)), "i_deg"),
                        (lambda: TrackConfig(scenario="default", rate_hz=np.float64(math.nan)), "rate_hz")):
        with pytest.raises(ConfigError, match=rf"^{name} = .*nan.*: expected a number \(not NaN\)"):
            build()
    assert OrbitConfig(raan_deg=np.float64(10.0)).raan_deg == 10.0


def test_a_renamed_field_takes_its_old_name_one_release_with_a_warning():
    """config.renamed_fields: the old name of a field in a file's table (under its dotted prefix), a constructor's
    keyword and an attribute read, each warned naming the new name and each the same field; a config replaced by
    the new name as any other; both names refused naming both; the written config holds the new name alone."""
    from envisat_pose.config import DeprecatedKeyWarning, renamed_fields, to_dict

    @renamed_fields(old_hz="rate_hz")
    @dataclass(frozen=True)
    class Renamed(Config):
        rate_hz: float = 1.0

    with pytest.warns(DeprecatedKeyWarning, match=r"^sensor\.old_hz is deprecated: use sensor\.rate_hz$"):
        assert from_dict(Renamed, {"old_hz": 2.0}, prefix="sensor") == Renamed(rate_hz=2.0)
    with pytest.warns(DeprecatedKeyWarning, match=r"^Renamed\.old_hz is deprecated: use Renamed\.rate_hz$"):
        built = Renamed(old_hz=3.0)
    assert dataclasses.replace(built, rate_hz=4.0) == Renamed(rate_hz=4.0) and to_dict(built) == {"rate_hz": 3.0}
    with pytest.warns(DeprecatedKeyWarning, match=r"^Renamed\.old_hz is deprecated"):
        assert built.old_hz == 3.0
    with pytest.raises(ConfigError, match=r"^sensor\.old_hz = 2\.0: expected sensor\.rate_hz alone \(old_hz is its "
                                          r"deprecated name\), not both: sensor\.rate_hz = 5\.0 is given too$"):
        from_dict(Renamed, {"old_hz": 2.0, "rate_hz": 5.0}, prefix="sensor")
    with pytest.raises(ConfigError, match=r"^Renamed\.old_hz = 2\.0: expected Renamed\.rate_hz alone"):
        Renamed(old_hz=2.0, rate_hz=5.0)
