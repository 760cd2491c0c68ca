"""Spacecraft appearance: procedural textures per covering class, and a per-image appearance drawn within each class.

Every geom of the target that the camera can see belongs to one covering class (multi-layer insulation foils,
radiator tiles, end panels, solar cells, boom metal, the ASAR antenna's tiles, instrument boxes). A face's class
never changes: +y (gold foil) never looks like -y (black foil), +z (silver foil) never like -z (radiator tiles),
so the half-turn about the long axis that swaps A<->C, B<->D, E<->G, F<->H stays visible in every image.
What varies per image, within the class: which of the class's textures, the base brightness and tint, and the
specular, shininess and reflectance of the material.

Textures are made with numpy from (texture_seed, class, index), built at first use and cached in the process
(never downloaded). The renderer declares one material per (geom, texture) pair; an appearance switches each geom's
`geom_matid` and writes that material's colour and specular terms into MuJoCo's model arrays before the
render, so the GL context is never rebuilt. Grey levels: the images are 8-bit grayscale, so the classes differ
in brightness and pattern, not only in hue.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field

import numpy as np

from envisat_pose.geometry import FACE_COVERING

TEXTURE_PX = 256  # side of every procedural texture, px

# Class of each geom (the MJCF's names). Appendage geoms are in geom group 4 (models/envisat.xml).
GEOM_CLASS = {
    **{f"face_{f}": c for f, c in FACE_COVERING.items()},  # the body's faces: the core's table
    "array": "solar_cells", "boom": "boom_metal",
    "asar": "asar_tiles", "asar_strut_fwd": "boom_metal", "asar_strut_aft": "boom_metal",
    "instr_meris": "mli_gold", "instr_aatsr": "mli_black", "instr_doris": "end_panel",
}
FACE_GEOMS = tuple(f"face_{f}" for f in FACE_COVERING)  # the main body's faces


def takes_class_appearance(geom_names) -> bool:
    """Whether a target takes the covering classes' appearance: its geoms are exactly those GEOM_CLASS names
    (models/envisat.xml's); any other target keeps its own materials, varied (draw_own_materials)."""
    return set(geom_names) == set(GEOM_CLASS)


@dataclass(frozen=True)
class CoveringClass:
    """How one class looks: base RGB (its hue), a range of base brightness multipliers (the class's own, which
    keeps paired faces apart), the metre size of one texture tile, and a specular weight."""

    rgb: tuple[float, float, float]
    brightness: tuple[float, float]
    tile_m: float
    specular_weight: float


CLASSES = {
    # foils: crinkled, specular; gold is mid-grey in an 8-bit grey image, silver bright, black kapton dark
    "mli_gold": CoveringClass((0.85, 0.66, 0.30), (0.75, 1.0), 1.5, 1.0),
    "mli_silver": CoveringClass((0.85, 0.85, 0.87), (0.85, 1.0), 1.5, 1.0),
    "mli_black": CoveringClass((0.20, 0.20, 0.21), (0.5, 1.0), 1.5, 1.0),
    # radiator: white-painted optical solar reflector tiles in a regular grid
    "radiator": CoveringClass((0.80, 0.80, 0.80), (0.6, 0.95), 1.0, 0.6),
    "end_panel": CoveringClass((0.30, 0.30, 0.32), (0.6, 1.0), 2.0, 0.3),
    "solar_cells": CoveringClass((0.20, 0.24, 0.42), (0.6, 1.0), 2.0, 0.8),
    "boom_metal": CoveringClass((0.62, 0.62, 0.64), (0.7, 1.0), 0.5, 0.7),
    "asar_tiles": CoveringClass((0.55, 0.55, 0.58), (0.7, 1.0), 1.3, 0.4),
}


@dataclass(frozen=True)
class GeomAppearance:
    """One geom's appearance in one image: class, texture index, RGB (base colour x brightness), specular, shininess,
    reflectance (MuJoCo's material terms, each in [0, 1])."""

    cls: str
    texture: int
    rgb: tuple[float, float, float]
    specular: float
    shininess: float
    reflectance: float


@dataclass(frozen=True)
class Appearance:
    """The appearance of one image: a GeomAppearance per target geom name (geoms not listed keep the MJCF's
    material), plus the lights: sun intensity and the Earth-shine light's intensity (0: none)."""

    materials: dict[str, GeomAppearance] = field(default_factory=dict)
    sun_intensity: float = 1.2
    earthshine_intensity: float = 0.0

    def to_json(self) -> dict:
        return {
            "sun_intensity": self.sun_intensity,
            "earthshine_intensity": self.earthshine_intensity,
            "materials": {g: {"class": m.cls, "texture": m.texture, "rgb": list(m.rgb), "specular": m.specular,
                              "shininess": m.shininess, "reflectance": m.reflectance}
                          for g, m in sorted(self.materials.items())},
        }

    @staticmethod
    def from_json(data: dict) -> "Appearance":
        mats = {g: GeomAppearance(m["class"], int(m["texture"]), tuple(m["rgb"]), m["specular"], m["shininess"],
                                  m["reflectance"]) for g, m in data.get("materials", {}).items()}
        return Appearance(mats, data["sun_intensity"], data["earthshine_intensity"])


def _r(v: float) -> float:
    """Rounded to 6 decimals: the label's text and the value rendered are the same number."""
    return round(float(v), 6)


def draw_materials(rng: np.random.Generator, set_size: int, specular: tuple[float, float],
                   shininess: tuple[float, float], reflectance: tuple[float, float],
                   brightness: tuple[float, float], geoms: tuple[str, ...],
                   classes: dict[str, str] | None = None) -> dict[str, GeomAppearance]:
    """A GeomAppearance per geom of `geoms`, drawn within its covering class (`classes`, GEOM_CLASS by default): a
    texture of the class's set_size, brightness = class range x the configured multiplier range, specular =
    class weight x the configured range, shininess and reflectance from their ranges."""
    classes = GEOM_CLASS if classes is None else classes
    out = {}
    for g in geoms:
        c = CLASSES[classes[g]]
        tex = int(rng.integers(0, set_size))
        b = rng.uniform(*c.brightness) * rng.uniform(*brightness)
        rgb = tuple(_r(min(1.0, v * b)) for v in c.rgb)
        out[g] = GeomAppearance(classes[g], tex, rgb, _r(c.specular_weight * rng.uniform(*specular)),
                                _r(rng.uniform(*shininess)), _r(rng.uniform(*reflectance)))
    return out


OWN_CLASS = "own"  # another target's appearance (envisat_pose/target.py): each geom's own material, varied


def draw_own_materials(rng: np.random.Generator, base_rgb: dict[str, tuple[float, float, float]],
                       specular: tuple[float, float], shininess: tuple[float, float], reflectance: tuple[float, float],
                       brightness: tuple[float, float]) -> dict[str, GeomAppearance]:
    """A GeomAppearance per geom of another target, over its own material: the material's RGB (base_rgb, its
    texture kept) times a brightness drawn from `brightness`, specular, shininess and reflectance from their
    ranges. Geoms in the order of base_rgb (the file's)."""
    out = {}
    for g, rgb in base_rgb.items():
        b = rng.uniform(*brightness)
        out[g] = GeomAppearance(OWN_CLASS, 0, tuple(_r(min(1.0, v * b)) for v in rgb), _r(rng.uniform(*specular)),
                                _r(rng.uniform(*shininess)), _r(rng.uniform(*reflectance)))
    return out


# ---------------------------------------------------------------------------------------------------------
# Procedural textures (grey patterns, mean near 0.8, modulating the material colour)


def _smooth_noise(rng: np.random.Generator, n: int, cells: int) -> np.ndarray:
    """Tileable smooth noise in [-1, 1]: a cells x cells random grid, bicubically upsampled with wrap. (n, n)."""
    import cv2

    g = rng.uniform(-1.0, 1.0, size=(cells, cells)).astype(np.float32)
    big = np.tile(g, (3, 3))  # wrap so the texture tiles without seams
    up = cv2.resize(big, (3 * n, 3 * n), interpolation=cv2.INTER_CUBIC)
    return up[n : 2 * n, n : 2 * n]


def _crinkle(rng: np.random.Generator, n: int) -> np.ndarray:
    """Crinkled foil: a height field of several octaves shaded by a random in-plane light direction (a
    normal-map shading baked into the albedo), with quilting seams. (n, n) in [0, 1]."""
    h = sum(_smooth_noise(rng, n, c) / (k + 1) for k, c in enumerate((6, 14, 32, 64)))
    gy, gx = np.gradient(h)
    a = rng.uniform(0, 2 * np.pi)
    shade = 0.78 + 6.0 * (np.cos(a) * gx + np.sin(a) * gy)
    shade += 0.08 * _smooth_noise(rng, n, 4)
    seam = int(rng.integers(2, 4))  # quilting tape across the blanket
    for k in range(seam):
        p = int(rng.integers(0, n))
        w = int(rng.integers(2, 5))
        if k % 2:
            shade[p : p + w, :] *= 0.55
        else:
            shade[:, p : p + w] *= 0.55
    return np.clip(shade, 0.0, 1.0)


def _tiles(rng: np.random.Generator, n: int, count: int, gap_px: int, jitter: float, base: float) -> np.ndarray:
    """A grid of count x count tiles with dark gaps and per-tile brightness jitter. (n, n) in [0, 1]."""
    size = n // count
    levels = base + jitter * rng.uniform(-1, 1, size=(count, count))
    img = np.kron(levels, np.ones((size, size)))
    img = np.pad(img, ((0, n - img.shape[0]), (0, n - img.shape[1])), mode="edge")
    idx = np.arange(n) % size
    gap = (idx < gap_px)
    img[gap, :] *= 0.3
    img[:, gap] *= 0.3
    return np.clip(img + 0.02 * _smooth_noise(rng, n, 8), 0.0, 1.0)


def _solar(rng: np.random.Generator, n: int) -> np.ndarray:
    """Solar cells: a grid of dark cells with bright gaps and busbars, a bright frame on the tile edge."""
    cells = int(rng.integers(6, 10))
    size = n // cells
    idx = np.arange(n) % size
    img = np.full((n, n), 0.55) + 0.08 * rng.uniform(-1, 1, size=(cells + 1, cells + 1)).repeat(size, 0).repeat(size, 1)[:n, :n]
    gap = idx < 3
    img[gap, :] = 0.95
    img[:, gap] = 0.95
    bus = (idx == size // 3) | (idx == 2 * size // 3)
    img[:, bus] = np.maximum(img[:, bus], 0.8)
    img[:6, :] = img[-6:, :] = img[:, :6] = img[:, -6:] = 1.0  # the panel frame
    return np.clip(img, 0.0, 1.0)


def _brushed(rng: np.random.Generator, n: int) -> np.ndarray:
    """Brushed metal: fine streaks along one axis. (n, n) in [0, 1]."""
    streak = rng.uniform(-1, 1, size=n)
    import cv2

    streak = cv2.GaussianBlur(streak.reshape(1, -1).astype(np.float32), (0, 0), 1.5).ravel()
    return np.clip(0.8 + 0.12 * streak[None, :] + 0.05 * _smooth_noise(rng, n, 4), 0.0, 1.0)


def _panel(rng: np.random.Generator, n: int) -> np.ndarray:
    """Painted end panel: smooth with faint blotches and a few rivet lines."""
    img = 0.8 + 0.1 * _smooth_noise(rng, n, 5)
    for _ in range(int(rng.integers(1, 4))):
        p = int(rng.integers(8, n - 8))
        img[p : p + 2, :] *= 0.6
    return np.clip(img, 0.0, 1.0)


PATTERNS = {
    "mli_gold": _crinkle, "mli_silver": _crinkle, "mli_black": _crinkle,
    "radiator": lambda rng, n: _tiles(rng, n, int(rng.integers(6, 10)), 2, 0.08, 0.85),
    "end_panel": _panel,
    "solar_cells": _solar,
    "boom_metal": _brushed,
    "asar_tiles": lambda rng, n: _tiles(rng, n, 4, 4, 0.05, 0.75),
}


@functools.lru_cache(maxsize=256)
def class_texture(texture_seed: int, cls: str, index: int) -> np.ndarray:
    """Texture `index` of class `cls` for a texture set seed: RGB uint8 (TEXTURE_PX, TEXTURE_PX, 3), grey.

    Seeded by (texture_seed, class number, index): the same texture in every process; built once per process.
    """
    k = sorted(CLASSES).index(cls)
    rng = np.random.default_rng(np.random.SeedSequence(texture_seed, spawn_key=(k, index)))
    grey = PATTERNS[cls](rng, TEXTURE_PX)
    u8 = np.rint(np.clip(grey, 0.0, 1.0) * 255.0).astype(np.uint8)
    return np.repeat(u8[:, :, None], 3, axis=2)
