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
ice caps, deserts and vegetation in grey levels, and a cloud layer. A low orbit sees only a cap of arccos(R / r)
(~27 deg) about the point below it, magnified: random-mode views turn the Earth so that this cap lies on the
Earth's +x cap, which the renderer draws with its own mesh and a texture of the same planet ~10x finer
(earth_cap_texture). Textures are made at the first view that needs them, once per process and renderer.

Cost (1024 px, llvmpipe, one thread): ~+40-50 ms CPU per image that shows the Earth (a full-frame textured,
lit, 4x multisampled surface, mirrored in the foil); nothing when it is out of the frame.
"""

from __future__ import annotations

import functools
import math

import numpy as np

from envisat_pose.attitude import quat_to_rotmat, rotmat_to_quat
from envisat_pose.datagen.scenario import EARTH_RADIUS_M

# The Earth is drawn shrunk by this factor about the camera: same angular size, inside the far plane (287 km)
# for chaser orbits up to ~140 000 km radius; its nearest point stays ~400 m away even at 200 km altitude.
EARTH_SCALE = 0.002
EARTH_MESH_STEPS_DEG = (1.0, 2.0, 4.0, 8.0)  # latitude and longitude steps of the sphere meshes (levels of detail)
EARTH_LIMB_TOLERANCE_PX = 0.3  # the largest deviation of the drawn limb from the true circle
EARTH_ROTATION_RAD_S = 7.2921159e-5  # sidereal rotation rate about the N z axis (sequence mode)
EARTH_TEXTURE_SET_SIZE = 2  # procedural Earth textures per renderer, made at first use
# A low orbit sees a cap of arccos(R / r) about the point below it (26.7 deg at 7142 km): random-mode views turn
# the Earth so that this cap lies within CAP_HALF_ANGLE_DEG of the Earth's +x axis, where the renderer draws a
# cap mesh with its own texture, ~10x finer than the globe's (earth_cap_texture).
CAP_HALF_ANGLE_DEG = 34.0
CAP_TILT_MAX_DEG = 3.0  # random mode: the point below the chaser within this of the cap's centre
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
    """A random-mode Earth behind the target, from rng alone: (nadir_K (3,) unit, r_m, R_K_from_E (3, 3) the
    Earth's attitude: its detailed cap toward the chaser (facing_attitude), texture index).

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
    return nadir, r_m, facing_attitude(-nadir, rng), int(rng.integers(0, EARTH_TEXTURE_SET_SIZE))


def earth_quat_C(t_s: np.ndarray, R_N_from_C: np.ndarray, theta0_rad: float) -> np.ndarray:
    """The Earth's attitude in the chaser frame C along an orbit: its body frame E (z to the north pole, x to
    longitude 0) turns about N z at EARTH_ROTATION_RAD_S from the angle theta0_rad at t = 0, and
    R_C_from_E = R_N_from_C^T R_N_from_E. t_s (N,), R_N_from_C (N, 3, 3) -> quaternions (N, 4), w x y z."""

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


def cap_mesh(ring_step_deg: float = 1.0, azimuth_step_deg: float = 1.0) -> dict[str, np.ndarray]:
    """The unit sphere's cap about +x out to CAP_HALF_ANGLE_DEG, as rings every ring_step_deg and
    azimuth_step_deg (its limb, seen from a low orbit, within a small fraction of a pixel of the circle), with
    the azimuthal equidistant texture coordinates of cap_dirs: u = 0.5 + 0.5 (theta / cap) cos(phi),
    v = 0.5 + 0.5 (theta / cap) sin(phi), theta the angle from +x, phi the azimuth from +y toward +z. Same keys
    as sphere_mesh."""
    n_ring = int(round(CAP_HALF_ANGLE_DEG / ring_step_deg))
    n_az = int(round(360.0 / azimuth_step_deg))
    theta = np.radians(np.arange(1, n_ring + 1) * ring_step_deg)
    phi = np.arange(n_az) * 2 * math.pi / n_az
    T, P = np.meshgrid(theta, phi, indexing="ij")
    ring = np.stack([np.cos(T), np.sin(T) * np.cos(P), np.sin(T) * np.sin(P)], -1).reshape(-1, 3)
    rad = (T / math.radians(CAP_HALF_ANGLE_DEG)).ravel()
    uv = np.stack([0.5 + 0.5 * rad * np.cos(P).ravel(), 0.5 + 0.5 * rad * np.sin(P).ravel()], -1)
    vert = np.concatenate([[[1.0, 0.0, 0.0]], ring])
    uv = np.concatenate([[[0.5, 0.5]], uv])
    rv = lambda i, j: 1 + i * n_az + (j % n_az)  # noqa: E731
    j = np.arange(n_az)
    faces = [np.stack([np.zeros(n_az, dtype=int), rv(0, j), rv(0, j + 1)], -1)]
    for i in range(n_ring - 1):
        a, b, c, d = rv(i, j), rv(i, j + 1), rv(i + 1, j), rv(i + 1, j + 1)
        faces += [np.stack([a, c, d], -1), np.stack([a, d, b], -1)]
    face = np.concatenate(faces).astype(np.int64)
    return {"vertex": vert, "normal": vert.copy(), "texcoord": uv, "face": face}


def cap_visible(quat_C: np.ndarray | None, nadir_C: np.ndarray, r_m: float) -> bool:
    """Whether everything the chaser sees of the Earth (the cap of arccos(R / r) about the point below it) lies
    within the cap mesh (CAP_HALF_ANGLE_DEG about the Earth's +x axis) for the Earth's attitude quat_C
    (w x y z, in C; None: the identity) and the unit-free nadir direction nadir_C (in C)."""

    R_C_from_E = np.eye(3) if quat_C is None else quat_to_rotmat(np.asarray(quat_C, dtype=float))
    up_E = R_C_from_E.T @ -(np.asarray(nadir_C, dtype=float) / np.linalg.norm(nadir_C))  # toward the chaser
    off = math.acos(max(-1.0, min(1.0, float(up_E[0]))))
    seen = math.acos(min(1.0, EARTH_RADIUS_M / float(r_m)))
    return off + seen <= math.radians(CAP_HALF_ANGLE_DEG) - math.radians(0.25)


def facing_attitude(up_K: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """R_K_from_E (3, 3): an Earth attitude whose cap centre (+x_E) points within CAP_TILT_MAX_DEG of up_K (the
    unit direction from the Earth's centre to the chaser, in K), with a uniform roll about it."""
    up = np.asarray(up_K, dtype=float) / np.linalg.norm(up_K)
    helper = np.array([1.0, 0.0, 0.0]) if abs(up[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(up, helper)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(up, e1)
    tilt = math.radians(CAP_TILT_MAX_DEG) * math.sqrt(rng.uniform())  # uniform on the small disc
    az = rng.uniform(0.0, 2.0 * math.pi)
    x = math.cos(tilt) * up + math.sin(tilt) * (math.cos(az) * e1 + math.sin(az) * e2)
    roll = rng.uniform(0.0, 2.0 * math.pi)
    a = np.cross(x, helper if abs(float(x @ helper)) < 0.9 else np.array([0.0, 0.0, 1.0]))
    a /= np.linalg.norm(a)
    b = np.cross(x, a)
    y = math.cos(roll) * a + math.sin(roll) * b
    return np.stack([x, y, np.cross(x, y)], axis=1)


@functools.lru_cache(maxsize=1)
def cap_mesh_xml_attributes() -> dict[str, str]:
    """The cap mesh as MJCF <mesh> attributes, built once per process."""
    return _xml_attributes(cap_mesh())


@functools.lru_cache(maxsize=8)
def mesh_xml_attributes(step_deg: float) -> dict[str, str]:
    """The sphere mesh as MJCF <mesh> attributes (vertex, normal, texcoord, face), built once per process."""
    return _xml_attributes(sphere_mesh(step_deg))


def _xml_attributes(m: dict[str, np.ndarray]) -> dict[str, str]:
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


def _planet(rng: np.random.Generator, dirs: np.ndarray) -> dict[str, np.ndarray]:
    """The large shapes of one planet at the unit vectors dirs (..., 3), from the 3D noise lattices drawn
    first from rng (the same planet whatever the map): continents, climate (arid or green), the cloud field
    and |latitude| (rad). (...) float32 each."""
    lat = np.abs(np.arcsin(np.clip(dirs[..., 2], -1, 1))).astype(np.float32)
    continents = _fbm3(rng, dirs, (3, 5, 9, 17, 33))
    climate = _fbm3(rng, dirs, (4, 9))
    clouds = _fbm3(rng, dirs, (6, 13, 27, 55, 111))
    lat_deg = np.degrees(lat)
    storm_belt = np.exp(-0.5 * ((lat_deg - 50.0) / 12.0) ** 2) + 0.6 * np.exp(-0.5 * (lat_deg / 8.0) ** 2)
    return {"continents": continents, "climate": climate, "clouds": clouds + 0.6 * storm_belt.astype(np.float32),
            "lat": lat}


def _compose(f: dict[str, np.ndarray], detail: np.ndarray, fine: np.ndarray, micro: np.ndarray) -> np.ndarray:
    """Albedo to RGB uint8 (..., 3) from the planet's fields (upsampled to the map) and detail noise at about
    4 deg (detail), 1 deg (fine) and finer (micro): land ~30 %, ocean ~0.05, vegetation ~0.13, desert ~0.38,
    ice ~0.75, clouds up to 0.8 (their share ~0.4, densest in the storm belts)."""
    c = f["continents"] + 0.10 * detail + 0.03 * fine + 0.01 * micro
    land = _smoothstep(0.52, 0.56, c)
    arid = _smoothstep(0.0, 1.0, f["climate"] + 0.2 * detail) * (1.0 - _smoothstep(0.6, 0.9, f["lat"]))
    land_grey = 0.13 + 0.25 * arid + 0.02 * fine + 0.02 * micro
    ice = _smoothstep(1.24, 1.30, f["lat"] + 0.05 * detail + 0.02 * fine)
    ocean_grey = 0.05 + 0.005 * detail
    surface = ocean_grey * (1.0 - land) + land_grey * land
    surface = surface * (1.0 - ice) + 0.75 * ice
    cl = f["clouds"] + 0.25 * detail + 0.1 * fine + 0.08 * micro
    cloud = 0.8 * _smoothstep(0.5, 1.7, cl) ** 1.5
    grey = surface * (1.0 - cloud) + cloud
    # a faint tint (the image is grey; MuJoCo's RGB to grey keeps the luminance)
    tint = np.stack([grey * 0.95, grey, grey * 1.08 + 0.02 * (1.0 - land) * (1.0 - cloud)], -1)
    out = np.rint(np.clip(tint, 0.0, 1.0) * 255.0).astype(np.uint8)
    out.setflags(write=False)
    return out


def _noise2(rng: np.random.Generator, h: int, w: int, cells: int) -> np.ndarray:
    """Smooth 2D noise over an (h, w) map with `cells` random values across its width (bicubic, no wrap).
    (h, w) float32, roughly unit spread."""
    import cv2

    ch = max(2, int(round(cells * h / w)))
    g = rng.standard_normal((ch + 4, cells + 4)).astype(np.float32)
    sx, sy = w / cells, h / ch
    up = cv2.resize(g, (int(round((cells + 4) * sx)), int(round((ch + 4) * sy))), interpolation=cv2.INTER_CUBIC)
    x0, y0 = int(round(2 * sx)), int(round(2 * sy))
    return up[y0 : y0 + h, x0 : x0 + w]


def _resize(field: np.ndarray, h: int, w: int) -> np.ndarray:
    import cv2

    return cv2.resize(field.astype(np.float32), (w, h), interpolation=cv2.INTER_CUBIC)


@functools.lru_cache(maxsize=4)
def earth_texture(seed: int, width_px: int, index: int = 0) -> np.ndarray:
    """Equirectangular Earth texture `index` of the set seeded by `seed`: RGB uint8 (width / 2, width, 3),
    longitude -180..180 deg along the width, north pole in row 0 (the whole globe, for distant views and for
    sequence mode; _compose gives the albedos)."""
    rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(0xEA27, index)))
    w = int(width_px)
    h = w // 2
    lh, lw = min(h, 256), min(w, 512)  # the large shapes on a coarse grid, upsampled
    fields = {k: _upsample(v, h, w) for k, v in _planet(rng, _sphere_dirs(lh, lw)).items()}
    # the equirectangular detail fades out above 70 deg of latitude, where its columns converge on the pole
    polar_fade = np.clip(3.0 * np.cos(math.pi / 2 - (np.arange(h) + 0.5) * math.pi / h), 0.0, 1.0)[:, None]
    detail = _detail2(rng, h, w, 96) * polar_fade  # ~4 deg cells: coastlines, cloud edges
    fine = _detail2(rng, h, w, 360) * polar_fade  # ~1 deg cells
    return _compose(fields, detail, fine, np.zeros_like(fine))


def cap_dirs(h: int, w: int) -> tuple[np.ndarray, np.ndarray]:
    """Unit vectors (h, w, 3) of the texel centres of a cap texture (azimuthal equidistant about +x, the cap's
    rim CAP_HALF_ANGLE_DEG at the inscribed circle) and their radius in the map (h, w), 1 at the rim."""
    v, u = np.meshgrid((np.arange(h) + 0.5) / h * 2 - 1, (np.arange(w) + 0.5) / w * 2 - 1, indexing="ij")
    rad = np.hypot(u, v)
    theta = rad * math.radians(CAP_HALF_ANGLE_DEG)
    phi = np.arctan2(v, u)
    dirs = np.stack([np.cos(theta), np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi)], -1)
    return dirs, rad


@functools.lru_cache(maxsize=4)
def earth_cap_texture(seed: int, width_px: int, index: int = 0) -> np.ndarray:
    """The cap of Earth texture `index` (the same planet as earth_texture's, from the same lattices) about
    its +x axis out to CAP_HALF_ANGLE_DEG, in the azimuthal equidistant map of cap_mesh, with detail down to
    ~0.1 deg: what a low orbit sees below it. RGB uint8 (width, width, 3)."""
    rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(0xEA27, index)))
    w = int(width_px)
    cw = min(w, 384)
    dirs, _ = cap_dirs(cw, cw)
    fields = {k: _resize(v, w, w) for k, v in _planet(rng, dirs).items()}
    span = 2.0 * CAP_HALF_ANGLE_DEG  # degrees across the map
    detail = _noise2(rng, w, w, int(round(span / 3.75)))
    fine = _noise2(rng, w, w, int(round(span / 1.0)))
    micro = _noise2(rng, w, w, min(w // 3, int(round(span / 0.15))))
    return _compose(fields, detail, fine, micro)
