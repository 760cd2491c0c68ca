"""The factory's scene with a target in it (envisat_pose.target reads the target file).

A file that holds the factory's camera (models/envisat.xml) is its own scene, rendered as it is. Any other target
file's body `target` goes into ENVISAT's scene in place of ENVISAT's body, attached by MuJoCo itself (MjSpec):
the target file's own <compiler> (angle unit, eulerseq, meshdir, texturedir), defaults and assets apply to its
body as they do to the file alone, so the body has the shape MuJoCo gives the file. The scene adds the free joint
`target_free` and the relative-gravity plugin; the chaser and its camera, the far clipping plane and the sun are
the same for every target, the near plane is ENVISAT's scaled by the target's size (size_ratio: a CubeSat seen as
near as its size allows is not clipped); the renderer adds the Earth. The target's assets carry the prefix `target/` (no clash with
the scene's own); its body, geoms and sites keep their names.
"""

from __future__ import annotations

import functools
import math
import xml.etree.ElementTree as ET
from dataclasses import dataclass

import numpy as np

from envisat_pose.geometry import model_path
from envisat_pose.target import Target, default_target, load_target
from envisat_pose.target_file import target_spec
from envisat_pose.target_fused import full_numbers, set_compiled_geom, set_compiled_site
from envisat_pose.target_rays import compiled_alone

ASSET_PREFIX = "target/"
SCENE_TARGET_POS_M = (0.0, 50.0, 0.0)  # where the scene's target body starts (the sim sets its state)
# The mean silhouette (size_ratio): its view directions, a Fibonacci lattice on the half sphere (a direction and its
# opposite outline the same), and the side of the square grid, 2 reach_m across, each outline is filled on.
SILHOUETTE_DIRECTIONS = 64
SILHOUETTE_GRID_PX = 512
_SUBPIXEL_BITS = 4  # fixed-point fraction bits of the filled triangles' corners (cv2.fillConvexPoly's shift)


def _scene_spec(target: Target):
    """ENVISAT's scene spec with ENVISAT's body (and the materials only it used) out and the target file's body
    attached, with the free joint and the gravity plugin."""
    import mujoco

    scene = mujoco.MjSpec.from_file(model_path())
    old = scene.body("target")
    own_materials = {g.material for g in old.geoms} - {g.material for g in scene.geoms if g.parent.name != "target"}
    instance = scene.plugins[0]
    plugin = (instance.name, instance.plugin_name, dict(instance.config))
    scene.delete(old)  # (MuJoCo drops the plugin instance with the body that used it: added back below)
    for mat in list(scene.materials):
        if mat.name in own_materials:
            scene.delete(mat)
    again = scene.add_plugin(name=plugin[0], plugin_name=plugin[1], active=True)
    again.config = plugin[2]
    child = target_spec(target.path)  # fused where the target body has child bodies
    child.option = scene.option  # the scene's physics: a file's own <option> (a template's gravity) has no say
    child.visual = scene.visual  # and its rendering: a file's own <visual> (clip planes, a viewer's) neither
    frame = scene.worldbody.add_frame(pos=list(SCENE_TARGET_POS_M))
    body = frame.attach_body(child.body("target"), ASSET_PREFIX, "")
    body.name = "target"
    body.pos, body.quat = [0.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0]
    for i, geom in enumerate(body.geoms):  # appearance draws and masks address geoms by name
        geom.name = target.geoms[i].name
    for site in body.sites:
        site.name = site.name.removeprefix(ASSET_PREFIX)
    body.add_freejoint(name="target_free")
    body.plugin.name, body.plugin.active = plugin[0], True
    return scene


def full_precision(text: str, target: Target) -> str:
    """The scene text with the target body's numbers as the file alone compiles them, to the last bit: MuJoCo's
    to_xml writes 6 significant digits (an inertia 1e-6 off turns a tumble 2e-5 rad away in 30 minutes; a site
    3 um off). The inertial becomes MuJoCo's principal moments and axes in T (added where the file states none),
    each site its position and orientation, each geom its compiled numbers (target_fused.set_compiled_geom: a
    primitive's pose and size, a fromto resolved; a mesh's pose less its own centring, which the scene applies
    again)."""
    root = ET.fromstring(text)
    body = next(b for b in root.iter("body") if b.get("name") == "target")
    alone = compiled_alone(target)
    own = alone.body("target").id
    inertial = body.find("inertial")
    if inertial is None:  # a file without one: MuJoCo's inertia from its geoms, stated (the scene's compiler aside)
        inertial = ET.Element("inertial")
        body.insert(0, inertial)
    inertial.attrib.clear()
    # MuJoCo's own principal moments and axes (target.inertia_T_kg_m2 is R diag R^T of these): a tensor rebuilt
    # from them carries round-off that fails MuJoCo's A + B >= C where the file meets it with equality (a plate)
    inertial.attrib.update({"pos": "0 0 0", "mass": repr(target.mass_kg),
                            "diaginertia": full_numbers(alone.body_inertia[own]),
                            "quat": full_numbers(alone.body_iquat[own])})
    sites = [s for s in range(alone.nsite) if alone.site_bodyid[s] == own]
    for el, s in zip(body.findall("site"), sites):
        set_compiled_site(el, alone, s)
    geoms = [g for g in range(alone.ngeom) if alone.geom_bodyid[g] == own]
    for el, g in zip(body.findall("geom"), geoms):
        set_compiled_geom(el, alone, g)
    return ET.tostring(root, encoding="unicode")


def half_sphere_directions(n: int) -> np.ndarray:
    """n unit vectors spread evenly over the half sphere z > 0 (a Fibonacci lattice), (n, 3); fixed, no draws."""
    k = np.arange(n)
    z = (k + 0.5) / n
    phi = math.pi * (3.0 - math.sqrt(5.0)) * k
    r = np.sqrt(1.0 - z * z)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def silhouette_area_m2(triangles_T_m: np.ndarray, direction_T: np.ndarray, reach_m: float,
                       grid_px: int = SILHOUETTE_GRID_PX) -> float:
    """The area of the outline of triangles_T_m (F, 3, 3), m, seen along the unit vector direction_T (3,) from
    afar (orthographic), m^2: the union of the projected triangles filled on a grid_px square grid 2 reach_m
    across, centred on the origin (reach_m: the farthest vertex from it, m). Thin parts cover at least one cell."""
    import cv2

    helper = np.array([1.0, 0.0, 0.0]) if abs(direction_T[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = np.cross(direction_T, helper)
    u /= np.linalg.norm(u)
    v = np.cross(direction_T, u)
    cells = (np.stack([triangles_T_m @ u, triangles_T_m @ v], axis=-1) + reach_m) * (grid_px / (2.0 * reach_m))
    fixed = np.round(cells * (1 << _SUBPIXEL_BITS)).astype(np.int32)
    covered = np.zeros((grid_px, grid_px), np.uint8)
    for corners in fixed:
        cv2.fillConvexPoly(covered, corners, 1, cv2.LINE_8, _SUBPIXEL_BITS)
    return float(covered.mean()) * (2.0 * reach_m) ** 2


@functools.lru_cache(maxsize=16)
def _mean_silhouette_m2(path: str, sha256: str) -> float:
    target = load_target(path)
    mesh = target.mesh(appendages=True)
    triangles = mesh.vertices_T_m[mesh.faces]
    return float(np.mean([silhouette_area_m2(triangles, d, target.reach_m)
                          for d in half_sphere_directions(SILHOUETTE_DIRECTIONS)]))


def mean_silhouette_m2(target: Target) -> float:
    """The target's outline area averaged over the view directions (SILHOUETTE_DIRECTIONS), m^2, all its geoms
    drawn (appendages too, as random mode draws them): what its image covers, per squared range. ENVISAT 66.6
    m^2 (0.136 of its reach squared: the long thin array), the 3U CubeSat 0.0885 m^2 (1.04), the upper stage
    34.8 m^2 (1.07)."""
    return _mean_silhouette_m2(target.path, target.sha256)


def size_ratio(target: Target) -> float:
    """The target's size against ENVISAT's (ENVISAT 1 exactly, the 3U CubeSat 0.0364, the upper stage 0.722):
    random mode's default ranges and keep-out margin (generate_config.sized_random_m) and another target's near
    clipping plane are ENVISAT's times this. The square root of the mean silhouettes' ratio, so the target covers
    about the share of the image ENVISAT covers at its defaults; at least the reaches' ratio, so no view is nearer,
    in the target's own reach, than ENVISAT's are (a thin rod's ranges stay outside it)."""
    envisat = default_target()
    return max(math.sqrt(mean_silhouette_m2(target) / mean_silhouette_m2(envisat)), target.reach_m / envisat.reach_m)


def _clip_planes_m(model) -> tuple[float, float]:
    return float(model.vis.map.znear * model.stat.extent), float(model.vis.map.zfar * model.stat.extent)


@functools.lru_cache(maxsize=1)
def envisat_clip_planes_m() -> tuple[float, float]:
    """(znear_m, zfar_m) of ENVISAT's own scene, m: models/envisat.xml's <visual><map znear zfar> times its extent
    (0.575 m and 287 km)."""
    import mujoco

    return _clip_planes_m(mujoco.MjModel.from_xml_path(model_path()))


def sized_znear_m(target: Target) -> float:
    """The near clipping plane of another target's scene, m: ENVISAT's times size_ratio (the CubeSat's 21 mm, the
    upper stage's 0.415 m), so its nearest views, sized alike, clip no more than ENVISAT's."""
    return envisat_clip_planes_m()[0] * size_ratio(target)


def with_near_plane(text: str, znear_m: float) -> str:
    """A scene's MJCF text with <visual><map znear> set so that MuJoCo's near plane (map znear times the model's
    extent) lies at znear_m, m. The extent, and with it the far plane, the shadow box and the sun's distance, stay
    as the text compiles."""
    import mujoco

    extent_m = float(mujoco.MjModel.from_xml_string(text).stat.extent)
    root = ET.fromstring(text)
    visual = root.find("visual")
    if visual is None:
        visual = ET.SubElement(root, "visual")
    map_el = visual.find("map")
    if map_el is None:
        map_el = ET.SubElement(visual, "map")
    map_el.set("znear", repr(znear_m / extent_m))
    return ET.tostring(root, encoding="unicode")


@functools.lru_cache(maxsize=16)
def _scene_text(path: str, sha256: str, own_scene: bool) -> str:
    if own_scene:
        with open(path, encoding="utf-8") as fh:
            return fh.read()
    target = load_target(path)
    return with_near_plane(full_precision(_scene_spec(target).to_xml(), target), sized_znear_m(target))


@functools.lru_cache(maxsize=16)
def _scene_clip_planes_m(path: str, sha256: str) -> tuple[float, float]:
    import mujoco

    return _clip_planes_m(mujoco.MjModel.from_xml_string(scene_xml(load_target(path))))


def scene_clip_planes_m(target: Target) -> tuple[float, float]:
    """(znear_m, zfar_m) of the factory's scene with `target` in it, m: what the renderer clips at (ENVISAT's own
    scene: 0.575 m and 287 km; another target: sized_znear_m and the far plane of ENVISAT's scene around it)."""
    return _scene_clip_planes_m(target.path, target.sha256)


def scene_xml(target: Target) -> str:
    """The MJCF text of the factory's scene with `target` in it (a file that is its own scene: as it is).
    MuJoCo writes the attached body in its compiled terms: quaternions (to 6 digits), defaults resolved."""
    return _scene_text(target.path, target.sha256, target.own_scene)


@dataclass(frozen=True)
class TargetScene:
    """What the factory needs of a target's scene without GL: geom_names (G,) of body 'target' in file order;
    mask_values {geom: 1..G} (a file that names its geoms after the factory's classes: render_view.MASK_VALUES);
    base_rgb {geom: (3,)} of each geom's material (or its own rgba), the colour another target's appearance draws
    vary."""

    geom_names: tuple[str, ...]
    mask_values: dict
    base_rgb: dict


def target_scene(target: Target) -> TargetScene:
    """The TargetScene of a target, from its Target."""
    names = tuple(g.name for g in target.geoms)
    return TargetScene(names, {name: min(i + 1, 255) for i, name in enumerate(names)},
                       {g.name: g.rgb for g in target.geoms})
