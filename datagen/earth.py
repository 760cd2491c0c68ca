"""The Earth behind the target: a procedural, seeded Earth texture, the sphere mesh it is drawn on, and the
geometry that places it at the right apparent size and direction.

The renderer draws the Earth as a textured mesh sphere (a UV sphere: equirectangular texture coordinates) shrunk
by EARTH_SCALE about the camera: the same angular radius asin(R / r) about the same nadir direction, but inside
the far plane. Meshes of several grid steps (EARTH_MESH_STEPS_DEG) are compiled; each view uses the coarsest
whose limb is within EARTH_LIMB_TOLERANCE_PX of the true circle (mesh_step_for): a distant Earth's whole
hemisphere is in the frame and costs triangles, a near one shows a short stretch of limb that needs a fine grid. MuJoCo lights it with the scene's sun, so the day side, the night side and the terminator between
them come from the sun's direction; the mask and depth never see it (background).

The texture (equirectangular, longitude along the width, north up) is made with numpy from a seed: continents
from smoothed noise on the sphere (no seam at the date line or pinch at the poles for the large shapes), ocean,
ice caps, deserts and vegetation in grey levels, and a cloud layer. Built once per process and renderer.
"""

from __future__ import annotations

import functools
import math

import numpy as np

from envisat_pose.datagen.scenario import EARTH_RADIUS_M

# The Earth is drawn shrunk by this factor about the camera: same angular size, inside the far plane (287 km)
# for chaser orbits up to ~140 000 km radius; its nearest point stays ~400 m away even at 200 km altitude.
EARTH_SCALE = 0.002
EARTH_MESH_STEPS_DEG = (1.0, 2.0, 4.0, 8.0)  # latitude and longitude steps of the sphere meshes (levels of detail)
EARTH_LIMB_TOLERANCE_PX = 0.3  # the largest deviation of the drawn limb from the true circle
EARTH_ROTATION_RAD_S = 7.2921159e-5  # sidereal rotation rate about the N z axis (sequence mode)
EARTH_TEXTURE_SET_SIZE = 2  # procedural Earth textures per renderer, made at first use
MAX_BACKDROP_DRAWS = 100  # random mode: nadir draws until the disc is in the frame and the sun not behind it


# ---------------------------------------------------------------------------------------------------------
# Geometry


def angular_radius_rad(r_m: float) -> float:
    """Angular radius of the Earth's disc seen from distance r_m of its centre: asin(R / r), rad."""
    return math.asin(min(1.0, EARTH_RADIUS_M / float(r_m)))


def pixel_rays_K(resolution_px: int, K: np.ndarray, step_px: int = 1) -> np.ndarray:
    """Unit rays of the pixel centres (every step_px-th along each axis and the last) in the camera frame K
    (x right, y down, z boresight). (h, w, 3)."""
    idx = np.unique(np.r_[np.arange(0, resolution_px, step_px), resolution_px - 1]).astype(float)
    u, v = np.meshgrid(idx, idx)
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], axis=-1)
    return rays / np.linalg.norm(rays, axis=-1, keepdims=True)


def disc_on_rays(rays_K: np.ndarray, nadir_K: np.ndarray, r_m: float) -> bool:
    """Whether any of the unit rays (M, 3) passes within the Earth's disc: the cone of half-angle
    asin(R / r_m) about the nadir direction nadir_K (3,), all in K."""
    n = np.asarray(nadir_K, dtype=float)
    return bool((rays_K @ (n / np.linalg.norm(n))).max() > math.cos(angular_radius_rad(r_m)))


def earth_in_frame(nadir_K: np.ndarray, r_m: float, K: np.ndarray, resolution_px: int) -> bool:
    """Whether any part of the Earth's disc falls on the image, checked on the pixel rays 8 px apart and
    along the border (a sliver of disc narrower than that may be missed). nadir_K (3,) in K, r_m: the
    distance of the Earth's centre, m."""
    return disc_on_rays(pixel_rays_K(resolution_px, K, 8).reshape(-1, 3), nadir_K, r_m)


def limb_error_px(step_deg: float, r_m: float, f_px: float) -> float:
    """Worst deviation (px) of a UV-sphere mesh's silhouette from the true limb: the sag of a cell's diagonal
    chord, R (1 - cos(step / sqrt 2)), seen across the limb distance sqrt(r^2 - R^2) at focal length f_px."""
    sag_m = EARTH_RADIUS_M * (1.0 - math.cos(math.radians(step_deg) / math.sqrt(2.0)))
    limb_m = math.sqrt(max(float(r_m) ** 2 - EARTH_RADIUS_M**2, 1.0))
    return f_px * sag_m / limb_m


def mesh_step_for(r_m: float, f_px: float) -> float:
    """The coarsest EARTH_MESH_STEPS_DEG step whose limb error (limb_error_px) is within
    EARTH_LIMB_TOLERANCE_PX at distance r_m and focal length f_px; the finest step when none is."""
    ok = [s for s in EARTH_MESH_STEPS_DEG if limb_error_px(s, r_m, f_px) <= EARTH_LIMB_TOLERANCE_PX]
    return max(ok) if ok else min(EARTH_MESH_STEPS_DEG)


def draw_backdrop(rng: np.random.Generator, r_range_m: tuple[float, float], K: np.ndarray,
                  resolution_px: int, sun_K: np.ndarray | None) -> tuple[np.ndarray, float, np.ndarray, int]:
    """A random-mode Earth behind the target, from rng alone: (nadir_K (3,) unit, r_m, quat (4,) w x y z of the
    Earth's attitude (uniform), texture index).

    r_m is uniform in r_range_m (the chaser's orbit radius); the nadir's angle off the boresight is uniform in
    [0, asin(R / r) + the image's half diagonal] (uniform in angle, not on the cap: the disc covers much of the
    image in most of these views), its azimuth uniform; drawn again (at most MAX_BACKDROP_DRAWS times) until
    some of the disc is on the image and the sun (sun_K, unit, in K; None in eclipse) is not behind it.
    """
    r_m = float(rng.uniform(*r_range_m))
    rho = angular_radius_rad(r_m)
    half_diag = math.atan(math.hypot(K[0, 2] + 0.5, K[1, 2] + 0.5) / K[0, 0])
    rays = pixel_rays_K(resolution_px, K, 8).reshape(-1, 3)
    for _ in range(MAX_BACKDROP_DRAWS):
        theta = rng.uniform(0.0, min(math.pi, rho + half_diag))
        phi = rng.uniform(0.0, 2.0 * math.pi)
        nadir = np.array([math.sin(theta) * math.cos(phi), math.sin(theta) * math.sin(phi), math.cos(theta)])
        sun_clear = sun_K is None or float(np.dot(sun_K, nadir)) < math.cos(rho)
        if sun_clear and disc_on_rays(rays, nadir, r_m):
            break
    return nadir, r_m, random_rotation_quat(rng), int(rng.integers(0, EARTH_TEXTURE_SET_SIZE))


def earth_quat_C(t_s: np.ndarray, R_N_from_C: np.ndarray, theta0_rad: float) -> np.ndarray:
    """The Earth's attitude in the chaser frame C along an orbit: its body frame E (z to the north pole, x to
    longitude 0) turns about N z at EARTH_ROTATION_RAD_S from the angle theta0_rad at t = 0, and
    R_C_from_E = R_N_from_C^T R_N_from_E. t_s (N,), R_N_from_C (N, 3, 3) -> quaternions (N, 4), w x y z."""
    from envisat_pose.attitude import rotmat_to_quat

    R_N_from_E = np.stack([rotation_z(theta0_rad + EARTH_ROTATION_RAD_S * t) for t in np.asarray(t_s, dtype=float)])
    return rotmat_to_quat(np.swapaxes(R_N_from_C, 1, 2) @ R_N_from_E)


def random_rotation_quat(rng: np.random.Generator) -> np.ndarray:
    """A uniformly random attitude as a unit quaternion (w, x, y, z). (4,)"""
    q = rng.standard_normal(4)
    q /= np.linalg.norm(q)
    return q if q[0] >= 0 else -q


def rotation_z(angle_rad: float) -> np.ndarray:
    """R (3, 3) of a rotation by angle_rad about z."""
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


# ---------------------------------------------------------------------------------------------------------
# The sphere mesh


def sphere_mesh(step_deg: float) -> dict[str, np.ndarray]:
    """A unit UV sphere with equirectangular texture coordinates: vertex (V, 3), normal (V, 3), texcoord (V, 2)
    (u = longitude from -180 deg at 0 to +180 deg at 1, v = 0 at the north pole: MuJoCo's texture rows run
    top-down), face (F, 3) counter-clockwise seen from outside. The date line has its own column of vertices
    at u = 0 and u = 1; each pole has one vertex per longitude cell, so no triangle is degenerate."""
    n_lon, n_lat = int(round(360.0 / step_deg)), int(round(180.0 / step_deg))
    lat = math.pi / 2 - np.arange(n_lat + 1) * math.pi / n_lat  # north to south
    lon = -math.pi + np.arange(n_lon + 1) * 2 * math.pi / n_lon
    LAT, LON = np.meshgrid(lat[1:-1], lon, indexing="ij")  # rings between the poles
    ring = np.stack([np.cos(LAT) * np.cos(LON), np.cos(LAT) * np.sin(LON), np.sin(LAT)], -1).reshape(-1, 3)
    ring_uv = np.stack([(LON + math.pi) / (2 * math.pi), (math.pi / 2 - LAT) / math.pi], -1).reshape(-1, 2)
    n_ring = n_lat - 1
    u_mid = (np.arange(n_lon) + 0.5) / n_lon
    north = np.tile([0.0, 0.0, 1.0], (n_lon, 1))
    south = np.tile([0.0, 0.0, -1.0], (n_lon, 1))
    vert = np.concatenate([north, ring, south])
    uv = np.concatenate([np.stack([u_mid, np.zeros(n_lon)], -1), ring_uv, np.stack([u_mid, np.ones(n_lon)], -1)])
    off = n_lon  # ring vertex (i, j) -> off + i * (n_lon + 1) + j
    rv = lambda i, j: off + i * (n_lon + 1) + j  # noqa: E731
    j = np.arange(n_lon)
    faces = [np.stack([j, rv(0, j), rv(0, j + 1)], -1)]  # north cap (pole, west, east)
    for i in range(n_ring - 1):
        a, b, c, d = rv(i, j), rv(i, j + 1), rv(i + 1, j), rv(i + 1, j + 1)
        faces += [np.stack([a, c, d], -1), np.stack([a, d, b], -1)]
    s0 = off + n_ring * (n_lon + 1)
    faces.append(np.stack([s0 + j, rv(n_ring - 1, j + 1), rv(n_ring - 1, j)], -1))  # south cap
    face = np.concatenate(faces).astype(np.int64)
    return {"vertex": vert, "normal": vert.copy(), "texcoord": uv, "face": face}


@functools.lru_cache(maxsize=8)
def mesh_xml_attributes(step_deg: float) -> dict[str, str]:
    """The sphere mesh as MJCF <mesh> attributes (vertex, normal, texcoord, face), built once per process."""
    m = sphere_mesh(step_deg)
    num = lambda a: " ".join(f"{v:.7g}" for v in a.ravel())  # noqa: E731
    return {"vertex": num(m["vertex"]), "normal": num(m["normal"]), "texcoord": num(m["texcoord"]),
            "face": " ".join(map(str, m["face"].ravel()))}


# ---------------------------------------------------------------------------------------------------------
# The texture


def earth_texture_width(resolution_px: int) -> int:
    """Texture width for a render resolution: 2 x the image side, within [512, 2048] px (at 1024 px one texel
    is 0.18 deg of longitude, ~20 km; the disc's detail near the limb is foreshortened anyway)."""
    return int(min(2048, max(512, 2 * int(resolution_px))))


def _sphere_dirs(h: int, w: int) -> np.ndarray:
    """Unit vectors (h, w, 3) of the texel centres of an equirectangular map (row 0 at the north pole)."""
    lat = math.pi / 2 - (np.arange(h) + 0.5) * math.pi / h
    lon = -math.pi + (np.arange(w) + 0.5) * 2 * math.pi / w
    LAT, LON = np.meshgrid(lat, lon, indexing="ij")
    return np.stack([np.cos(LAT) * np.cos(LON), np.cos(LAT) * np.sin(LON), np.sin(LAT)], -1)


def _noise3(rng: np.random.Generator, dirs: np.ndarray, cells: int) -> np.ndarray:
    """Smooth noise on the sphere: a cells^3 lattice of N(0, 1) values, cubic-spline interpolated at the unit
    vectors dirs (..., 3). No seams: the field lives in 3D. (...) float32, spread ~0.5-1."""
    from scipy.ndimage import map_coordinates

    grid = rng.standard_normal((cells + 3,) * 3).astype(np.float32)
    pts = (dirs.reshape(-1, 3).T + 1.0) * 0.5 * (cells - 1) + 1.0
    return map_coordinates(grid, pts, order=3, mode="nearest").reshape(dirs.shape[:-1]).astype(np.float32)


def _fbm3(rng: np.random.Generator, dirs: np.ndarray, cells: tuple[int, ...]) -> np.ndarray:
    """Fractal noise: octaves of _noise3 at the given lattice sizes, amplitude halving, normalised to unit
    standard deviation. (...) float32."""
    f = sum(_noise3(rng, dirs, c) * 0.5**k for k, c in enumerate(cells))
    return (f - f.mean()) / f.std()


def _detail2(rng: np.random.Generator, h: int, w: int, cells_w: int) -> np.ndarray:
    """Fine noise on the equirectangular grid: a (cells_w / 2, cells_w) random grid upsampled bicubically,
    wrapped in longitude. (h, w) float32, roughly unit spread."""
    import cv2

    cells_h = max(2, cells_w // 2)
    g = rng.standard_normal((cells_h, cells_w)).astype(np.float32)
    pad = 2
    gw = np.concatenate([g[:, -pad:], g, g[:, :pad]], axis=1)
    up = cv2.resize(gw, (int(round(w * (cells_w + 2 * pad) / cells_w)), h), interpolation=cv2.INTER_CUBIC)
    x0 = int(round(w * pad / cells_w))
    return up[:, x0 : x0 + w]


def _upsample(field: np.ndarray, h: int, w: int) -> np.ndarray:
    """Bicubic upsampling of an equirectangular field to (h, w), wrapped in longitude."""
    import cv2

    fh, fw = field.shape
    pad = 2
    fwp = np.concatenate([field[:, -pad:], field, field[:, :pad]], axis=1)
    scale = w / fw
    up = cv2.resize(fwp, (int(round((fw + 2 * pad) * scale)), h), interpolation=cv2.INTER_CUBIC)
    x0 = int(round(pad * scale))
    return up[:, x0 : x0 + w]


def _smoothstep(lo: float, hi: float, x: np.ndarray) -> np.ndarray:
    t = np.clip((x - lo) / (hi - lo), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


@functools.lru_cache(maxsize=4)
def earth_texture(seed: int, width_px: int, index: int = 0) -> np.ndarray:
    """Equirectangular Earth texture `index` of the set seeded by `seed`: RGB uint8 (width / 2, width, 3),
    longitude -180..180 deg along the width, north pole in row 0.

    Grey levels follow the albedos seen from orbit: ocean ~0.06, vegetation ~0.12, desert ~0.3, ice ~0.8,
    clouds up to ~0.9 (their share ~0.5, densest in the mid-latitude and equatorial belts); about 30 % land.
    """
    rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(0xEA27, index)))
    w = int(width_px)
    h = w // 2
    lh, lw = min(h, 256), min(w, 512)  # the large shapes on a coarse grid, upsampled
    dirs = _sphere_dirs(lh, lw)
    lat = np.abs(np.arcsin(np.clip(dirs[..., 2], -1, 1)))
    continents = _fbm3(rng, dirs, (3, 5, 9, 17, 33))
    climate = _fbm3(rng, dirs, (4, 9))
    clouds_big = _fbm3(rng, dirs, (6, 13, 27, 55, 111))
    storm_belt = np.exp(-0.5 * ((np.degrees(lat) - 50.0) / 12.0) ** 2) + 0.6 * np.exp(-0.5 * (np.degrees(lat) / 8.0) ** 2)
    up = lambda f: _upsample(f.astype(np.float32), h, w)  # noqa: E731
    # the equirectangular detail fades out above 70 deg of latitude, where its columns converge on the pole
    polar_fade = np.clip(3.0 * np.cos(math.pi / 2 - (np.arange(h) + 0.5) * math.pi / h), 0.0, 1.0)[:, None]
    detail = _detail2(rng, h, w, 96) * polar_fade  # ~4 deg cells: coastlines, cloud edges
    fine = _detail2(rng, h, w, 360) * polar_fade  # ~1 deg cells
    c = up(continents) + 0.10 * detail + 0.03 * fine
    land = _smoothstep(0.52, 0.56, c)  # ~30 % of the sphere above the threshold
    lat_f = up(lat.astype(np.float32))
    arid = _smoothstep(0.0, 1.0, up(climate) + 0.2 * detail) * (1.0 - _smoothstep(0.6, 0.9, lat_f))
    land_grey = 0.13 + 0.25 * arid + 0.02 * fine
    ice = _smoothstep(1.24, 1.30, lat_f + 0.05 * detail + 0.02 * fine)
    ocean_grey = 0.05 + 0.005 * detail
    surface = ocean_grey * (1.0 - land) + land_grey * land
    surface = surface * (1.0 - ice) + 0.75 * ice
    cl = up(clouds_big) + 0.6 * up(storm_belt.astype(np.float32)) + 0.25 * detail + 0.08 * fine
    cloud = 0.9 * _smoothstep(0.5, 1.7, cl) ** 1.5
    grey = surface * (1.0 - cloud) + cloud
    # a faint tint (the image is grey; MuJoCo's RGB to grey keeps the luminance)
    tint = np.stack([grey * 0.95, grey, grey * 1.08 + 0.02 * (1.0 - land) * (1.0 - cloud)], -1)
    out = np.rint(np.clip(tint, 0.0, 1.0) * 255.0).astype(np.uint8)
    out.setflags(write=False)
    return out
