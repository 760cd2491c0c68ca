"""A mix of looks for online training (pipelines/detector/online.py) and its TOML file: WeightedLook (a name, a weight and
a GenerateConfig each; resolutions, cameras, scenarios may differ), read_looks / looks_toml, and which look and
sample each frame of the mix is.

The weights are rounded to whole shares of LOOK_PERIOD frames (each look at least one), and the frames of a
period are dealt out evenly (look_pattern): frame f = c LOOK_PERIOD + p is sample i = c n_j + r_p of look j =
pattern[p], r_p the count of look j's entries before p. A random-mode look's sample i is its dataset's sample i
(the sample `envisat generate` would make); a sequence-mode look's is frame i mod L of its sequence q = i // L
(L = its num_images), the sequence of the look's config with seed sequence_seed(seed, q): fresh sequences as the
run goes, each rendered in order of its frames (look_sample).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from envisat_pose.config import check, flatten, from_dict, load_toml, resolve_job_config, to_dict, to_toml
from envisat_pose.datagen.generate_config import GenerateConfig

LOOK_PERIOD = 100  # a mix of looks repeats its order every LOOK_PERIOD frames: the weights in whole percent
SEQUENCE_KEY = 0x5E0  # a sequence look's q-th sequence: seed SeedSequence([seed, SEQUENCE_KEY, q])


@dataclass(frozen=True)
class WeightedLook:
    """One kind of frame in an online run: name, generate (a GenerateConfig, random or sequence mode: its
    resolution, appearance, camera, scenario) and weight (its share of the frames, relative to the other looks')."""

    name: str
    generate: object
    weight: float = 1.0

    def __post_init__(self) -> None:
        mode = getattr(self.generate, "mode", None)
        check(mode in ("random", "sequence"), f"looks.{self.name}.mode", mode, "'random' or 'sequence'")
        check(isinstance(self.weight, (int, float)) and np.isfinite(self.weight) and self.weight > 0,
              f"looks.{self.name}.weight", self.weight, "a positive number")

    def record(self) -> dict:
        return {"name": self.name, "weight": float(self.weight), "generate": to_dict(self.generate)}

    @classmethod
    def from_record(cls, record: dict, where: str = "looks") -> "WeightedLook":
        """A look from its record ({name, weight, generate} as record() writes it; ConfigError naming the field)."""

        check(isinstance(record, dict) and isinstance(record.get("name"), str), f"{where}.name",
              record.get("name") if isinstance(record, dict) else record, "a look's name (a string)")
        name = record["name"]
        return cls(name, from_dict(GenerateConfig, record.get("generate", {}), f"{where}.{name}.generate"),
                   record.get("weight", 1.0))


def read_looks(path: str) -> tuple[WeightedLook, ...]:
    """The looks of a TOML file: each [[look]] table a name, a weight and the keys of `envisat generate
    --config` (mode 'random' unless given); keys outside the [[look]] tables are every look's defaults (a look's
    own win). InputError or ConfigError naming the file's field."""

    data = load_toml(path)
    entries = data.pop("look", None)
    check(isinstance(entries, list) and len(entries) >= 1 and all(isinstance(e, dict) for e in entries), "look",
          entries, f"one or more [[look]] tables in {path}")
    looks = []
    for n, entry in enumerate(entries):
        entry = dict(entry)
        name = entry.pop("name", None)
        check(isinstance(name, str) and name != "", f"look[{n}].name", name, "a look's name (a string)")
        weight = entry.pop("weight", 1.0)
        # the file's shared keys under the look's own (its tables key by key)
        cfg = resolve_job_config(GenerateConfig, {"mode": "random", **data}, None, flatten(entry),
                                 prefix=f"look.{name}")
        looks.append(WeightedLook(name, cfg, weight))
    return as_looks(looks)


def looks_toml(looks) -> str:
    """The looks as read_looks reads them back (each look's whole config)."""

    return "".join("[[look]]\n" + to_toml(dict(name=look.name, weight=float(look.weight),
                                                **to_dict(look.generate)), prefix="look.") + "\n"
                   for look in as_looks(looks))


def as_looks(looks) -> tuple[WeightedLook, ...]:
    """A GenerateConfig (one look, 'default') or a sequence of Looks, as a tuple of Looks with distinct names."""
    if hasattr(looks, "mode"):
        return (WeightedLook("default", looks),)
    looks = tuple(looks)
    check(1 <= len(looks) <= LOOK_PERIOD, "looks", len(looks), f"1 to {LOOK_PERIOD} looks")
    names = [look.name for look in looks]
    check(len(set(names)) == len(names), "looks", names, "looks with distinct names")
    return looks


def look_shares(looks) -> np.ndarray:
    """Each look's frames in a period of LOOK_PERIOD (int64, sum LOOK_PERIOD, each at least 1): the weights'
    shares rounded by largest remainder."""
    w = np.array([look.weight for look in as_looks(looks)], dtype=np.float64)
    exact = w / w.sum() * LOOK_PERIOD
    n = np.maximum(np.floor(exact).astype(np.int64), 1)
    while n.sum() < LOOK_PERIOD:
        n[np.argmax(exact - n)] += 1
    while n.sum() > LOOK_PERIOD:
        n[np.argmax(np.where(n > 1, n - exact, -np.inf))] -= 1
    return n


def look_pattern(shares: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The order of a period: (look (LOOK_PERIOD,) int64, rank (LOOK_PERIOD,) int64), look j's r-th entry placed
    at (r + 1/2) / n_j of the period (ties by look), so that every look is spread evenly over it."""
    entries = sorted(((r + 0.5) / n, j, r) for j, n in enumerate(shares) for r in range(int(n)))
    return (np.array([j for _, j, _ in entries], dtype=np.int64), np.array([r for _, _, r in entries],
                                                                         dtype=np.int64))


def frame_look(frame: int, shares: np.ndarray, pattern: tuple[np.ndarray, np.ndarray]) -> tuple[int, int]:
    """(look j, its sample i) of frame `frame` of the mix (the module doc)."""
    c, p = divmod(int(frame), LOOK_PERIOD)
    j = int(pattern[0][p])
    return j, c * int(shares[j]) + int(pattern[1][p])


def sequence_seed(seed: int, q: int) -> int:
    """The seed of a sequence look's q-th sequence."""
    return int(np.random.SeedSequence([seed, SEQUENCE_KEY, q]).generate_state(1, dtype=np.uint32)[0])


def max_side(looks) -> int:
    """The largest frame side among the looks (the slots' side)."""
    return max(look.generate.resolution_px for look in as_looks(looks))


def renderer_key(gen_cfg) -> tuple:
    """What a SceneRenderer is built from: (side, shadows, texture set size, texture seed, Earth seed, target)."""
    return (gen_cfg.resolution_px, gen_cfg.shadows,
            gen_cfg.appearance.texture_set_size if gen_cfg.appearance_on else 0, gen_cfg.appearance.texture_seed,
            gen_cfg.earth_seed, gen_cfg.target)



def look_sample(gen_cfg, i: int) -> tuple:
    """(config, index) of a look's sample i: a random-mode look's dataset sample i; a sequence-mode look's frame
    i mod L of its sequence i // L (the look's config with that sequence's seed)."""
    if gen_cfg.mode == "random":
        return gen_cfg, i
    from dataclasses import replace

    q, k = divmod(i, gen_cfg.num_images)
    return replace(gen_cfg, seed=sequence_seed(gen_cfg.seed, q)), k
