"""The truth scenario: the chaser's orbit, the target's tumble, the initial relative state, the time grid.

Defaults are the reference sheet's (docs/reference.md, sections 2 and 6): a 50 m V-bar hold on a
7142 km, e = 0.001 orbit, ENVISAT spinning with a 134.74 s period. One frozen config per job, validated when
built (envisat_pose.config.Config). Named scenarios are the TOML files of scenarios/ (read by
envisat_pose.named_scenarios); this module takes their truth part, and computes the Earth's shadow for
scenarios with an [eclipse] table.
"""

from __future__ import annotations

import math
import sys
from dataclasses import dataclass, field

import numpy as np

from envisat_pose.config import Config, check, deep_update, from_dict
from envisat_pose.datagen.orbit import chaser_orbit
from envisat_pose.datagen.target_scene import size_ratio
from envisat_pose.named_scenarios import known, names, table, truth_part
from envisat_pose.target import DEFAULT_TARGET, load_target

EARTH_RADIUS_M = 6378137.0  # WGS-84 equatorial radius, used only to reject orbits inside the Earth
MIN_PHYSICS_DT_S = 1e-4  # s: RK4 at 0.05 s is already exact to 1e-8 m over an orbit (reference sheet)
MAX_OUTPUT_STEPS = 10_000_000  # samples of a truth's output grid
MAX_PHYSICS_STEPS = 50_000_000  # RK4 steps per simulation: ~100k steps/s, so at most ~10 minutes
# the most a body may turn in one RK4 step of the truth: at 0.05 rad the torque-free energy and momentum hold to
# ~1e-8 over minutes; a 1 s step of a tumble at 0.79 rad/s (8 s period) drifted the energy 0.27 % in 120 s
MAX_TURN_PER_PHYSICS_STEP_RAD = 0.05
# the Earth's Hill sphere, m: a_E (m_E / 3 M_S)^(1/3) = 1.496e11 m x 0.01; beyond it the Sun's pull dominates, so
# a Keplerian orbit about the Earth (the chaser's, the shadow's) describes nothing
EARTH_HILL_RADIUS_M = 1.5e9
# an orbit angle beyond one turn either way names an angle within it (and at 1e17 deg a double's step is 16 deg)
MAX_ORBIT_ANGLE_DEG = 360.0
# the slowest spin the truth's tumble bound can take: max_body_rate_rad_s squares the body rate, and below
# sqrt(2.2e-308) rad/s (the least normal double's root) the square is 0 (a still target: no bound to divide by)
MIN_SPIN_RATE_RAD_S = math.sqrt(sys.float_info.min)


@dataclass(frozen=True)
class OrbitConfig(Config):
    """The chaser's (chief's) Keplerian orbit. Angles in degrees; the true anomaly is at t = 0."""

    mu_m3_s2: float = 3.986004418e14
    a_m: float = 7142.0e3
    e: float = 0.001
    i_deg: float = 98.4
    raan_deg: float = 0.0
    argp_deg: float = 90.0
    nu0_deg: float = 30.0

    def validate(self, prefix: str = "") -> None:
        p = f"{prefix}." if prefix else ""
        check(self.mu_m3_s2 > 0, f"{p}mu_m3_s2", self.mu_m3_s2, "a positive gravitational parameter in m^3/s^2")
        check(0.0 <= self.e < 1.0, f"{p}e", self.e, "an eccentricity in [0, 1) (closed orbit)")
        check(self.a_m * (1.0 - self.e) > EARTH_RADIUS_M, f"{p}a_m", self.a_m,
              f"a semi-major axis whose perigee a(1-e) lies above the Earth's surface ({EARTH_RADIUS_M:.0f} m)")
        check(0.0 <= self.i_deg <= 180.0, f"{p}i_deg", self.i_deg, "an inclination in [0, 180] deg")
        check(self.a_m * (1.0 + self.e) <= EARTH_HILL_RADIUS_M, f"{p}a_m", self.a_m,
              f"a semi-major axis whose apogee a(1+e) lies within the Earth's Hill sphere ({EARTH_HILL_RADIUS_M:.1e} "
              "m; beyond it the Sun, not the Earth, holds the orbit)")
        for name in ("raan_deg", "argp_deg", "nu0_deg"):
            value = getattr(self, name)
            check(abs(value) <= MAX_ORBIT_ANGLE_DEG, f"{p}{name}", value,
                  f"an angle in [-{MAX_ORBIT_ANGLE_DEG:g}, {MAX_ORBIT_ANGLE_DEG:g}] deg (one turn either way)")

    @property
    def perigee_rate_rad_s(self) -> float:
        """The orbit's fastest turn, rad/s: its true anomaly's rate at perigee, h / r_p^2 (h = sqrt(mu a (1-e^2)))."""
        return math.sqrt(self.mu_m3_s2 * self.a_m * (1.0 - self.e ** 2)) / (self.a_m * (1.0 - self.e)) ** 2

    @property
    def n_rad_s(self) -> float:
        """Mean motion, rad/s."""
        return math.sqrt(self.mu_m3_s2 / self.a_m**3)

    @property
    def period_s(self) -> float:
        return 2.0 * math.pi / self.n_rad_s


@dataclass(frozen=True)
class TargetConfig(Config):
    """The target's tumble: inertial angular velocity w_t0 = (2 pi / spin_period_s) * unit(spin_axis_T), in T.

    p0_mrp: initial MRP of T relative to C; omitted (None) draws a uniformly random attitude from the seed.
    gravity_gradient: whether the truth applies the gravity-gradient torque (the filter model does not).
    file: the target's MJCF file (envisat_pose/target.py; default ENVISAT): its body `target`'s inertia drives the
    tumble, its sites are the keypoints.
    """

    spin_period_s: float = 134.74
    spin_axis_T: tuple[float, float, float] = (0.12, -0.20, 1.0)
    p0_mrp: tuple[float, float, float] | None = None
    gravity_gradient: bool = False
    file: str = DEFAULT_TARGET

    def validate(self, prefix: str = "") -> None:
        p = f"{prefix}." if prefix else ""
        check(0 < self.spin_period_s <= 2.0 * math.pi / MIN_SPIN_RATE_RAD_S, f"{p}spin_period_s", self.spin_period_s,
              f"a positive period in seconds, at most {2.0 * math.pi / MIN_SPIN_RATE_RAD_S:.3g} s (a slower body rate "
              "squares to 0 in the tumble's bound)")
        with np.errstate(over="ignore"):
            norm = float(np.linalg.norm(np.asarray(self.spin_axis_T, dtype=float)))
        check(np.isfinite(norm) and norm > 0, f"{p}spin_axis_T", list(self.spin_axis_T),
              "a non-zero vector of finite length")

        load_target(self.file, f"{p}file")  # a bad target file: one line before any work
        if self.p0_mrp is not None:
            check(np.linalg.norm(self.p0_mrp) <= 1.0 + 1e-12, f"{p}p0_mrp", list(self.p0_mrp),
                  "an MRP with |p| <= 1 (use the shadow set -p/|p|^2)")

    @property
    def w0_T_rad_s(self) -> np.ndarray:
        axis = np.asarray(self.spin_axis_T, dtype=float)
        return 2.0 * math.pi / self.spin_period_s * axis / np.linalg.norm(axis)


@dataclass(frozen=True)
class RelativeConfig:
    """Initial relative translation of the target with respect to the chaser, in C (LVLH)."""

    rho0_C_m: tuple[float, float, float] = (0.0, 50.0, 0.0)
    rhodot0_C_m_s: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def check_outside(self, radius_m: float, prefix: str = "relative", size_ratio: float | None = None) -> None:
        """ConfigError unless |rho0| exceeds radius_m, the target's keypoints' circumscribed radius (ENVISAT: its
        main body's corners, 5.29 m); size_ratio, where given, the target's size against ENVISAT's
        (target_scene.size_ratio), for the way on: the start `envisat run` and `generate --mode sequence` fly,
        said only where it clears the radius (a smaller target's scaled start comes nearer, not farther)."""
        rng = float(np.linalg.norm(self.rho0_C_m))

        def scaled(v) -> str:
            return "[" + ", ".join(f"{size_ratio * x:.4g}" for x in v) + "]"

        way_on = "" if size_ratio is None or size_ratio * rng <= radius_m else (
            f": start it farther, as `envisat run` and `generate --mode sequence` do (the start scaled by the "
            f"target's size, {size_ratio:.3g} times): a config file's [relative] rho0_C_m = {scaled(self.rho0_C_m)}, "
            f"rhodot0_C_m_s = {scaled(self.rhodot0_C_m_s)}")
        check(rng > radius_m, f"{prefix}.rho0_C_m", list(self.rho0_C_m),
              f"a range above {radius_m:.2f} m (the main body's circumscribed radius); "
              f"|rho0| = {rng:.2f} m puts the chaser inside the target{way_on}")


@dataclass(frozen=True)
class ScenarioConfig(Config):
    """A truth simulation: physics, initial state and output grid (t = 0, dt_s, ... <= duration_s).

    keepout_margin_m: the least distance, m, the chaser may come to any part of the target (body, boom,
    solar array) along the simulated trajectory; a scenario that comes closer is refused after simulation.
    scenario: the named scenario the config was made from ('' for none; scenario_config and resolve_job set it),
    recorded in its truth: `envisat estimate --truth` takes that scenario's filter and measurement tables.
    """

    orbit: OrbitConfig = field(default_factory=OrbitConfig)
    target: TargetConfig = field(default_factory=TargetConfig)
    relative: RelativeConfig = field(default_factory=RelativeConfig)
    duration_s: float = 1800.0
    dt_s: float = 1.0
    max_physics_dt_s: float = 0.05
    keepout_margin_m: float = 2.0
    seed: int = 0
    scenario: str = ""

    def validate(self, prefix: str = "") -> None:
        p = f"{prefix}." if prefix else ""
        check(self.scenario == "" or known(self.scenario), f"{p}scenario", self.scenario,
              "'' or a named scenario (" + ", ".join(names()) + ") or a scenario file that exists")
        check(self.duration_s > 0, f"{p}duration_s", self.duration_s, "a positive duration in seconds")
        check(self.dt_s >= MIN_PHYSICS_DT_S, f"{p}dt_s", self.dt_s, f"an output step of at least {MIN_PHYSICS_DT_S:g} "
              "s (the least physics step: each output step holds one or more)")
        check(self.dt_s <= self.duration_s, f"{p}duration_s", self.duration_s,
              f"a duration of at least one output step (dt_s = {self.dt_s:g} s)")
        check(self.duration_s / self.dt_s <= MAX_OUTPUT_STEPS, f"{p}duration_s", self.duration_s,
              f"at most {MAX_OUTPUT_STEPS:.0e} output steps of dt_s = {self.dt_s:g} s (a shorter duration_s or a "
              "longer dt_s)")
        check(MIN_PHYSICS_DT_S <= self.max_physics_dt_s <= 1.0, f"{p}max_physics_dt_s", self.max_physics_dt_s,
              f"a physics step in [{MIN_PHYSICS_DT_S:g}, 1] s (RK4 accuracy; smaller steps only cost time)")
        steps = (self.n_out - 1) * self.substeps
        check(steps <= MAX_PHYSICS_STEPS, f"{p}max_physics_dt_s", self.max_physics_dt_s,
              f"at most {MAX_PHYSICS_STEPS:.0e} RK4 steps in all; duration_s = {self.duration_s:g} s at "
              f"{self.physics_dt_s:g} s per step needs {steps:.3g} (raise max_physics_dt_s or shorten duration_s)")
        check(self.keepout_margin_m >= 0, f"{p}keepout_margin_m", self.keepout_margin_m,
              "a non-negative distance in m")
        check(0 <= self.seed < 2**63, f"{p}seed", self.seed, "a non-negative integer seed")

        target = load_target(self.target.file, f"{p}target.file")
        radius_m = float(np.linalg.norm(target.keypoints_T_m, axis=1).max())
        if np.linalg.norm(self.relative.rho0_C_m) <= radius_m:  # refused: say how far the sized start would be
            self.relative.check_outside(radius_m, f"{p}relative", size_ratio(target))
        w_max = max_body_rate_rad_s(self.target.w0_T_rad_s, target.inertia_T_kg_m2)
        check(w_max * MIN_PHYSICS_DT_S <= MAX_TURN_PER_PHYSICS_STEP_RAD, f"{p}target.spin_period_s",
              self.target.spin_period_s, f"a tumble the truth's RK4 can follow: at most {MAX_TURN_PER_PHYSICS_STEP_RAD:g} "
              f"rad per step of at least {MIN_PHYSICS_DT_S:g} s, a body rate of at most "
              f"{MAX_TURN_PER_PHYSICS_STEP_RAD / MIN_PHYSICS_DT_S:g} rad/s (this tumble reaches {w_max:.3g} rad/s)")
        orbit_rate = self.orbit.perigee_rate_rad_s
        check(self.physics_dt_s * orbit_rate <= MAX_TURN_PER_PHYSICS_STEP_RAD, f"{p}orbit.mu_m3_s2",
              self.orbit.mu_m3_s2, f"an orbit that turns at most {MAX_TURN_PER_PHYSICS_STEP_RAD:g} rad per physics "
              f"step of {self.physics_dt_s:g} s (RK4 accuracy): it turns {orbit_rate:.3g} rad/s at perigee")
        check(self.physics_dt_s * w_max <= MAX_TURN_PER_PHYSICS_STEP_RAD, f"{p}max_physics_dt_s",
              self.max_physics_dt_s, f"a physics step in which the tumble turns at most "
              f"{MAX_TURN_PER_PHYSICS_STEP_RAD:g} rad (RK4 accuracy): at most "
              f"{MAX_TURN_PER_PHYSICS_STEP_RAD / w_max:.3g} s for a body rate of up to {w_max:.3g} rad/s")
        check_start_in_orbit(self.orbit, self.relative, f"{p}relative")

    @property
    def n_out(self) -> int:
        """Number of output samples."""
        return int(math.floor(self.duration_s / self.dt_s + 1e-9)) + 1

    @property
    def physics_dt_s(self) -> float:
        """The RK4 step: the largest step <= max_physics_dt_s that divides dt_s."""
        return self.dt_s / self.substeps

    @property
    def substeps(self) -> int:
        return max(1, math.ceil(self.dt_s / self.max_physics_dt_s - 1e-9))


def max_body_rate_rad_s(w0_T_rad_s: np.ndarray, J_T_kg_m2: np.ndarray) -> float:
    """An upper bound on |w| over a torque-free tumble starting at w0, rad/s: in principal axes, x_i = w_i^2 >= 0
    keep sum J_i x_i (twice the energy) and sum J_i^2 x_i (|H|^2), so |w|^2 = sum x_i is at most the best vertex
    of that linear program (at most two x_i non-zero); w0's own |w| where the moments are equal."""
    J, axes = np.linalg.eigh(0.5 * (J_T_kg_m2 + J_T_kg_m2.T))
    x0 = np.square(axes.T @ np.asarray(w0_T_rad_s, dtype=float))
    energy, momentum = float(J @ x0), float(np.square(J) @ x0)
    best = float(x0.sum())
    for i, j in ((0, 1), (0, 2), (1, 2)):
        A = np.array([[J[i], J[j]], [J[i] ** 2, J[j] ** 2]])
        if abs(np.linalg.det(A)) <= 1e-12 * J[j] ** 3:
            continue
        xi, xj = np.linalg.solve(A, [energy, momentum])
        if xi >= -1e-12 * best and xj >= -1e-12 * best:
            best = max(best, xi + xj)
    return math.sqrt(best)


def check_start_in_orbit(orbit: OrbitConfig, relative: RelativeConfig, field_prefix: str) -> None:
    """ConfigError unless the target starts above the Earth's surface and on a closed orbit: its position r_c +
    rho0 and inertial velocity v_c + rhodot0 + w x rho0 in C (x radial out, y along-track, z the orbit normal;
    w = thetadot z), from the chaser's state at the true anomaly nu0."""
    nu = math.radians(orbit.nu0_deg)
    slr_m = orbit.a_m * (1.0 - orbit.e ** 2)
    r_c = slr_m / (1.0 + orbit.e * math.cos(nu))
    h = math.sqrt(orbit.mu_m3_s2 * slr_m)
    rho, rhodot = np.asarray(relative.rho0_C_m, float), np.asarray(relative.rhodot0_C_m_s, float)
    r_t = np.array([r_c, 0.0, 0.0]) + rho
    v_t = np.array([orbit.mu_m3_s2 / h * orbit.e * math.sin(nu), h / r_c, 0.0]) + rhodot \
        + np.cross([0.0, 0.0, h / r_c ** 2], rho)
    check(np.linalg.norm(r_t) > EARTH_RADIUS_M, f"{field_prefix}.rho0_C_m", list(relative.rho0_C_m),
          f"a start above the Earth's surface (the target {np.linalg.norm(r_t):.0f} m from its centre)")
    energy = 0.5 * float(v_t @ v_t) - orbit.mu_m3_s2 / float(np.linalg.norm(r_t))
    check(energy < 0.0, f"{field_prefix}.rhodot0_C_m_s", list(relative.rhodot0_C_m_s),
          f"a start on a closed orbit (the target's inertial speed {np.linalg.norm(v_t):.0f} m/s escapes)")


@dataclass(frozen=True)
class EclipseConfig(Config):
    """A scenario's [eclipse] table: sun_dir_N, the direction toward the sun in the inertial frame N (any length;
    the sun is taken as infinitely far). The Earth's shadow is a cylinder of one Earth radius along it."""

    sun_dir_N: tuple[float, float, float] = (1.0, 0.0, 0.0)

    def validate(self, prefix: str = "") -> None:
        p = f"{prefix}." if prefix else ""
        check(np.linalg.norm(self.sun_dir_N) > 0, f"{p}sun_dir_N", list(self.sun_dir_N), "a non-zero vector")


def scenario_dict(name: str) -> dict:
    """The truth's part of a named scenario (scenarios/NAME.toml): overrides of ScenarioConfig's defaults.
    Unknown names raise ConfigError listing the known ones."""
    return truth_part(name)


def truth_config_json(cfg: ScenarioConfig, target_sha256: str) -> str:
    """A truth's config_json: the scenario config (its `scenario`, the named scenario it was made from, where one
    was: `envisat estimate --truth` takes its filter and measurement tables) and the target file's sha256 when
    simulated (`target.sha256`: a truth read later refuses a file that has changed since). A config of no named
    scenario records no `scenario` key, as truths did before the field."""
    import dataclasses
    import json

    data = dataclasses.asdict(cfg)
    data["target"]["sha256"] = target_sha256
    if not cfg.scenario:
        del data["scenario"]
    return json.dumps(data, sort_keys=True)


def scenario_of_truth(config: dict) -> ScenarioConfig:
    """The validated ScenarioConfig of a truth's config (the target's sha256 record set aside; a scenario name no
    longer known read as none)."""
    target = {k: v for k, v in (config.get("target") or {}).items() if k != "sha256"}
    data = {**config, "target": target}
    if not known(data.get("scenario")):
        data.pop("scenario", None)
    return from_dict(ScenarioConfig, data)


def scenario_config(name: str = "default", **overrides) -> ScenarioConfig:
    """A validated named scenario with optional top-level overrides (duration_s=..., seed=...); its `scenario`
    field is name."""
    return from_dict(ScenarioConfig, deep_update({**scenario_dict(name), "scenario": name}, overrides), prefix="")


def sequence_scenario(name: str, range_scale: float, num_images: int, frame_dt_s: float, seed: int, target: str,
                      prefix: str = "") -> ScenarioConfig:
    """The truth an image-factory sequence of num_images frames frame_dt_s apart simulates: the named scenario of
    `target` (its file) started range_scale times as far (scaled_start), from `seed`. A sequence longer than a
    simulation takes (MAX_OUTPUT_STEPS frames, MAX_PHYSICS_STEPS RK4 steps at the scenario's physics step) is a
    ConfigError naming num_images under prefix, not the duration_s or dt_s it sets (no key of a generate config)."""
    start = {"seed": seed, "target": {"file": target}, **scaled_start(name, range_scale)}
    longest_s = MAX_PHYSICS_STEPS * scenario_config(name).max_physics_dt_s  # one frame's RK4 steps, at most
    check(frame_dt_s <= longest_s, f"{prefix}.sequence.frame_dt_s" if prefix else "sequence.frame_dt_s", frame_dt_s,
          f"a frame interval of at most {longest_s:g} s ({MAX_PHYSICS_STEPS:.0e} RK4 steps of scenario {name!r}'s "
          "max_physics_dt_s)")
    one = scenario_config(name, duration_s=frame_dt_s, dt_s=frame_dt_s, **start)  # its physics step
    most = min(MAX_OUTPUT_STEPS, MAX_PHYSICS_STEPS // one.substeps) + 1
    check(num_images <= most, f"{prefix}.num_images" if prefix else "num_images", num_images,
          f"at most {most} frames in sequence mode: scenario {name!r} simulates at most {MAX_OUTPUT_STEPS:.0e} "
          f"steps and {MAX_PHYSICS_STEPS:.0e} RK4 steps, {one.substeps} per frame at sequence.frame_dt_s = "
          f"{frame_dt_s:g} s")
    return scenario_config(name, duration_s=max(num_images - 1, 1) * frame_dt_s, dt_s=frame_dt_s, **start)


def scaled_start(name: str, scale: float) -> dict:
    """Overrides of a named scenario (for scenario_config) that start its chaser `scale` times as far: the initial
    relative position and velocity (relative.rho0_C_m, rhodot0_C_m_s) and the keep-out margin times scale. The
    relative motion is linear in its start to first order in range over the orbit radius (the Clohessy-Wiltshire
    model), so the whole relative trajectory scales with it: the same tumble seen from a hold sized to a smaller
    or larger target. {} for scale 1 (the scenario as written)."""
    if scale == 1.0:
        return {}
    cfg = scenario_config(name)
    return {"relative": {"rho0_C_m": [v * scale for v in cfg.relative.rho0_C_m],
                         "rhodot0_C_m_s": [v * scale for v in cfg.relative.rhodot0_C_m_s]},
            "keepout_margin_m": cfg.keepout_margin_m * scale}


def in_earth_shadow(r_N_m: np.ndarray, sun_dir_N) -> np.ndarray:
    """(N,) bool: positions r_N_m (N, 3) m inside the Earth's cylindrical shadow: behind the Earth (r . s < 0)
    and within one Earth radius (EARTH_RADIUS_M) of the sun line through the Earth's centre."""
    s = np.asarray(sun_dir_N, dtype=float)
    s = s / np.linalg.norm(s)
    along = r_N_m @ s
    perp = np.linalg.norm(r_N_m - along[:, None] * s, axis=1)
    return (along < 0) & (perp < EARTH_RADIUS_M)


def eclipse_windows(cfg: ScenarioConfig, eclipse: EclipseConfig) -> tuple[tuple[float, float], ...]:
    """The chaser's shadow passes over the scenario's output grid t = 0, dt_s, ... <= duration_s, as windows
    [start, end) in s (end: the first sample out of the shadow, or the last sample + dt_s)."""

    t_s = np.arange(cfg.n_out) * cfg.dt_s
    dark = in_earth_shadow(chaser_orbit(cfg.orbit, t_s).r_N_m, eclipse.sun_dir_N)
    edges = np.flatnonzero(np.diff(np.concatenate([[False], dark, [False]]).astype(np.int8)))
    return tuple((float(t_s[a]), float(t_s[b - 1] + cfg.dt_s)) for a, b in zip(edges[::2], edges[1::2]))


def scenario_eclipse(name: str) -> EclipseConfig | None:
    """The validated [eclipse] table of a named scenario, None if it has none."""
    data = table(name, "eclipse")
    return from_dict(EclipseConfig, data, prefix="eclipse") if data else None
