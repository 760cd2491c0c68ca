"""The target as an MJCF file: read, checked and placed into the factory's own scene.

A target file's worldbody holds one body named `target` with its `inertial` (mass, full inertia about the centre
of mass at the body's origin, in the body's own axes), its geoms and materials (meshes and textures relative to the
file) and its keypoints as the body's sites `kp_<name>`, in file order. The body frame of the file is the frame T
of the labels and the truth, whatever MuJoCo's principal axes are (MuJoCo keeps the body frame and puts the
principal axes in body_iquat). models/envisat.xml, the default, is its own scene and keeps its corner sites
`corner_A` .. `corner_H` as keypoints A-H.

scene_xml(target) puts another file's body into ENVISAT's scene in place of ENVISAT (free joint `target_free`, the
relative-gravity plugin, the chaser and its camera, the sun; the renderer adds the Earth): the one scene every
target shares, so the camera, the clipping planes and the lights are the same for all.
"""

from __future__ import annotations

import copy
import functools
import hashlib
import os
import xml.etree.ElementTree as ET
from dataclasses import dataclass

import numpy as np

from envisat_pose.attitude import quat_to_rotmat
from envisat_pose.config import ConfigError
from envisat_pose.geometry import CORNER_NAMES, model_path

ENVISAT_TARGET = "models/envisat.xml"  # the default `target` of every config (the package's file)
KEYPOINT_PREFIX = "kp_"
MIN_KEYPOINTS = 4
KEYPOINT_MAX_GEOM_DISTANCE_M = 0.05  # a keypoint farther than this from every geom of the target is refused
TARGET_CLASS = "target_file"  # the default class the target file's own <default> becomes in the scene
# ENVISAT's materials that only its target uses (left out of another target's scene)
_ENVISAT_TARGET_MATERIALS = ("panel", "foil", "foil_silver", "array", "boom", "asar", "instrument_black")


@dataclass(frozen=True)
class TargetModel:
    """A checked target file.

    name: the file's model name (<mujoco model=...>) or its stem. path: absolute path. sha256: of the file's
    bytes. keypoint_names: (K,) names, file order (ENVISAT: A-H). keypoint_sites: (K,) their MJCF site names.
    keypoints_T_m: (K, 3) in T, m. mass_kg; inertia_T_kg_m2: (3, 3) about the CoM in T.
    """

    name: str
    path: str
    sha256: str
    keypoint_names: tuple[str, ...]
    keypoint_sites: tuple[str, ...]
    keypoints_T_m: np.ndarray
    mass_kg: float
    inertia_T_kg_m2: np.ndarray

    @property
    def is_envisat(self) -> bool:
        return os.path.realpath(self.path) == os.path.realpath(model_path())

    def record(self, given: str) -> dict:
        """What a dataset's manifest records of its target: the path as given, the name, sha256, keypoints."""
        return {"file": given, "name": self.name, "sha256": self.sha256, "keypoint_names": list(self.keypoint_names)}


def resolve_target_path(given: str) -> str:
    """The file a `target` value names: ENVISAT_TARGET is the package's models/envisat.xml (ENVISAT_MODEL
    overrides it); any other path is taken as it is (relative to the working folder), or, when no such file
    exists and it starts with 'models/', the package's models folder."""
    if given == ENVISAT_TARGET:
        return os.path.abspath(model_path())
    if not os.path.exists(given) and given.startswith("models/"):
        packaged = os.path.join(os.path.dirname(model_path()), given[len("models/"):])
        if os.path.exists(packaged):
            return os.path.abspath(packaged)
    return os.path.abspath(given)


def _fail(field: str, given: str, expected: str):
    raise ConfigError(field, given, expected)


def _vec(text: str | None, n: int, default=None) -> np.ndarray | None:
    if text is None:
        return None if default is None else np.array(default, dtype=float)
    v = np.array([float(t) for t in text.split()])
    if len(v) != n:
        raise ValueError(f"{text!r}: expected {n} numbers")
    return v


def inertia_of(inertial: ET.Element) -> np.ndarray:
    """The (3, 3) inertia tensor in the body frame, kg m^2, of an <inertial> element (fullinertia, or
    diaginertia turned by its quat/euler-free orientation: only quat is read)."""
    full = inertial.get("fullinertia")
    if full is not None:
        xx, yy, zz, xy, xz, yz = _vec(full, 6)
        return np.array([[xx, xy, xz], [xy, yy, yz], [xz, yz, zz]])
    diag = _vec(inertial.get("diaginertia"), 3)
    if diag is None:
        raise ValueError("no fullinertia or diaginertia")

    q = _vec(inertial.get("quat"), 4, (1.0, 0.0, 0.0, 0.0))
    R = quat_to_rotmat(q / np.linalg.norm(q))
    return R @ np.diag(diag) @ R.T


def check_inertia(mass_kg: float, inertia: np.ndarray) -> str | None:
    """What is wrong with a rigid body's mass properties, or None: zero or negative mass, an inertia that is not
    symmetric positive definite, or principal moments that violate the triangle inequality (I1 <= I2 + I3)."""
    if not mass_kg > 0:
        return f"a positive mass (got {mass_kg:g} kg)"
    moments = np.linalg.eigvalsh(0.5 * (inertia + inertia.T))
    if not np.all(moments > 0):
        return f"a positive definite inertia (principal moments {np.round(moments, 6).tolist()} kg m^2)"
    a, b, c = sorted(moments)
    if c > a + b + 1e-9 * c:
        return f"principal moments that satisfy the triangle inequality (I3 = {c:g} > I1 + I2 = {a + b:g} kg m^2)"
    return None


def _target_body(root: ET.Element) -> ET.Element | None:
    world = root.find("worldbody")
    if world is None:
        return None
    return next((b for b in world.iter("body") if b.get("name") == "target"), None)


def _keypoints(body: ET.Element, envisat: bool) -> tuple[tuple[str, ...], tuple[str, ...], np.ndarray]:
    """(names, site names, (K, 3) positions in T) of the body's own sites: kp_<name>, or ENVISAT's corners."""
    sites = [s for s in body.findall("site")]
    if envisat:
        by_name = {s.get("name"): s for s in sites}
        chosen = [(c, f"corner_{c}", by_name[f"corner_{c}"]) for c in CORNER_NAMES if f"corner_{c}" in by_name]
    else:
        chosen = [(s.get("name")[len(KEYPOINT_PREFIX):], s.get("name"), s) for s in sites
                  if (s.get("name") or "").startswith(KEYPOINT_PREFIX)]
    pos = np.array([_vec(s.get("pos"), 3, (0.0, 0.0, 0.0)) for _, _, s in chosen]).reshape(-1, 3)
    return tuple(n for n, _, _ in chosen), tuple(s for _, s, _ in chosen), pos


def _resolve_files(root: ET.Element, folder: str) -> None:
    """Make the file attributes of meshes, textures and hfields absolute (relative to the file, its compiler's
    meshdir/texturedir), so the scene compiles from anywhere."""
    comp = root.find("compiler")
    meshdir = comp.get("meshdir", "") if comp is not None else ""
    texdir = comp.get("texturedir", "") if comp is not None else ""
    asset = root.find("asset")
    for el in ([] if asset is None else list(asset)):
        f = el.get("file")
        if f is not None and not os.path.isabs(f):
            sub = meshdir if el.tag in ("mesh", "skin") else texdir if el.tag == "texture" else ""
            el.set("file", os.path.normpath(os.path.join(folder, sub, f)))


def _scene_tree(target_root: ET.Element, folder: str) -> ET.Element:
    """ENVISAT's scene with ENVISAT's body and its own materials taken out and the target file's body, assets and
    defaults put in (the body at ENVISAT's initial place, with the free joint and the gravity plugin)."""
    scene = ET.parse(model_path()).getroot()
    world = scene.find("worldbody")
    world.remove(_target_body(scene))
    asset = scene.find("asset")
    for mat in list(asset):
        if mat.get("name") in _ENVISAT_TARGET_MATERIALS:
            asset.remove(mat)
    _resolve_files(target_root, folder)
    for el in list(target_root.find("asset") if target_root.find("asset") is not None else []):
        asset.append(copy.deepcopy(el))
    default = scene.find("default")
    own = ET.SubElement(default, "default", {"class": TARGET_CLASS})
    for d in target_root.findall("default"):
        for child in d:
            own.append(copy.deepcopy(child))
    body = copy.deepcopy(_target_body(target_root))
    for i, geom in enumerate(body.findall("geom")):
        geom.set("name", geom.get("name") or f"target_geom_{i}")  # looks and masks address geoms by name
    for key in ("pos", "quat", "euler", "axisangle", "xyaxes", "zaxis"):
        body.attrib.pop(key, None)
    body.set("pos", "0 50 0")
    body.set("childclass", body.get("childclass", TARGET_CLASS))
    body.insert(0, ET.Element("plugin", instance="relative_gravity"))
    body.insert(0, ET.Element("freejoint", name="target_free"))
    world.append(body)
    return scene


def scene_xml(target: TargetModel) -> str:
    """The MJCF text of the factory's scene with `target` in it (ENVISAT: models/envisat.xml as it is)."""
    if target.is_envisat:
        with open(target.path, encoding="utf-8") as fh:
            return fh.read()
    root = ET.parse(target.path).getroot()
    return ET.tostring(_scene_tree(root, os.path.dirname(target.path)), encoding="unicode")


@dataclass(frozen=True)
class TargetScene:
    """What the factory needs of a target's compiled scene without GL: geom_names (G,) of body 'target' in file
    order; mask_values {geom: 1..G} (ENVISAT: render.MASK_VALUES); base_rgb {geom: (3,)} of each geom's material
    (or its own rgba), the colour another target's looks vary."""

    geom_names: tuple[str, ...]
    mask_values: dict
    base_rgb: dict


@functools.lru_cache(maxsize=16)
def _target_scene(path: str, sha256: str) -> TargetScene:
    import mujoco

    model = mujoco.MjModel.from_xml_string(scene_xml(load_target(path)))
    body = model.body("target").id
    geoms = [g for g in range(model.ngeom) if model.geom_bodyid[g] == body]
    names = tuple(model.geom(g).name for g in geoms)
    rgb = {}
    for g, name in zip(geoms, names):
        mat = int(model.geom_matid[g])
        rgb[name] = tuple(float(v) for v in (model.mat_rgba[mat][:3] if mat >= 0 else model.geom_rgba[g][:3]))
    return TargetScene(names, {name: min(i + 1, 255) for i, name in enumerate(names)}, rgb)


def target_scene(target: TargetModel) -> TargetScene:
    """The TargetScene of another target (not ENVISAT: its geoms keep their covering classes)."""
    return _target_scene(target.path, target.sha256)


def _keypoint_distances_m(model, site_names: tuple[str, ...]) -> np.ndarray:
    """Distance of each keypoint site to the nearest geom of body `target`, m (MuJoCo's own geom distance to a
    probe sphere of 0.1 mm at the site), (K,)."""
    import mujoco

    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    body = model.body("target").id
    probe = model.geom("kp_probe").id
    pid = model.body("kp_probe").mocapid[0]
    geoms = [g for g in range(model.ngeom) if model.geom_bodyid[g] == body]
    out = np.full(len(site_names), np.inf)
    fromto = np.zeros(6)
    for k, s in enumerate(site_names):
        data.mocap_pos[pid] = data.site_xpos[model.site(s).id]
        mujoco.mj_kinematics(model, data)
        for g in geoms:
            d = mujoco.mj_geomDistance(model, data, probe, g, 1.0, fromto)
            out[k] = min(out[k], max(d + 1e-4, 0.0))
    return out


def _compile_checked(text: str, field: str, given: str, site_names: tuple[str, ...]):
    """Compile the scene (a mesh that does not load, a bad attribute: one line with MuJoCo's message) and check
    that every keypoint lies within KEYPOINT_MAX_GEOM_DISTANCE_M of a geom of the target."""
    import mujoco

    root = ET.fromstring(text)
    probe = ET.SubElement(root.find("worldbody"), "body", name="kp_probe", mocap="true", pos="0 0 -1e4")
    ET.SubElement(probe, "geom", name="kp_probe", type="sphere", size="0.0001", group="5")
    try:
        model = mujoco.MjModel.from_xml_string(ET.tostring(root, encoding="unicode"))
    except ValueError as err:
        said = " ".join(str(err).split())
        _fail(field, given, f"an MJCF file MuJoCo compiles (it says: {said})")
    dist = _keypoint_distances_m(model, site_names)
    k = int(np.argmax(dist))
    if dist[k] > KEYPOINT_MAX_GEOM_DISTANCE_M:
        _fail(field, given, f"keypoints on the target: site {site_names[k]!r} is {dist[k]:.3f} m from every geom "
                            f"(at most {KEYPOINT_MAX_GEOM_DISTANCE_M:g} m)")


@functools.lru_cache(maxsize=16)
def _load(path: str, mtime_ns: int, field: str, given: str) -> TargetModel:
    with open(path, "rb") as fh:
        raw = fh.read()
    try:
        root = ET.fromstring(raw)
    except ET.ParseError as err:
        _fail(field, given, f"an MJCF (XML) file ({err})")
    envisat = os.path.realpath(path) == os.path.realpath(model_path())
    body = _target_body(root)
    if body is None:
        _fail(field, given, "an MJCF file whose worldbody holds a body named 'target'")
    if body.find("body") is not None or body.find("joint") is not None or body.find("freejoint") is not None:
        if not envisat:
            _fail(field, given, "one rigid body 'target' (no child bodies, no joints: the scene adds its free joint)")
    names, sites, pos = _keypoints(body, envisat)
    if len(names) < MIN_KEYPOINTS:
        _fail(field, given, f"at least {MIN_KEYPOINTS} keypoint sites named '{KEYPOINT_PREFIX}<name>' on body "
                            f"'target' (found {len(names)})")
    if len(set(names)) != len(names):
        _fail(field, given, f"keypoint sites with distinct names (got {list(names)})")
    inertial = body.find("inertial")
    if inertial is None:
        _fail(field, given, "an <inertial> element on body 'target' (mass and full inertia about the CoM)")
    try:
        mass = float(inertial.get("mass", "nan"))
        inertia = inertia_of(inertial)
        com = _vec(inertial.get("pos"), 3, (0.0, 0.0, 0.0))
    except ValueError as err:
        _fail(field, given, f"a readable <inertial> on body 'target' ({err})")
    problem = check_inertia(mass, inertia)
    if problem is not None:
        _fail(field, given, f"body 'target' with {problem}")
    if not np.allclose(com, 0.0, atol=1e-9):
        _fail(field, given, f"the centre of mass at the body's origin (<inertial pos='0 0 0'>, got {com.tolist()}): "
                            "T's origin is the CoM")
    target = TargetModel(root.get("model") or os.path.splitext(os.path.basename(path))[0], path,
                         hashlib.sha256(raw).hexdigest(), names, sites, pos, mass, inertia)
    if not envisat:
        _compile_checked(scene_xml(target), field, given, sites)
    return target


def load_target(given: str, field: str = "target") -> TargetModel:
    """The checked target of a config's `target` value (a path; ENVISAT_TARGET is the package's ENVISAT).
    ConfigError naming `field`, the value and what was expected: no such file, not XML, no body 'target', fewer
    than 4 kp_ sites, no or a bad inertial (zero mass, not positive definite, the triangle inequality), the CoM
    off the body's origin, a scene MuJoCo does not compile (a mesh that does not load), a keypoint farther than
    KEYPOINT_MAX_GEOM_DISTANCE_M from every geom. Cached per file and modification time."""
    path = resolve_target_path(given)
    if not os.path.isfile(path):
        _fail(field, given, "an MJCF file (no such file)")
    return _load(path, os.stat(path).st_mtime_ns, field, given)


def envisat_target() -> TargetModel:
    return load_target(ENVISAT_TARGET)


def _only_envisat(verb: str) -> str:
    return (f"ENVISAT ({ENVISAT_TARGET}): `envisat {verb}` and the detector know ENVISAT's corners A-H only; "
            "another target's images and labels come from `envisat generate --target` (docs/usage.md)")


def require_envisat(given: str, field: str, verb: str) -> None:
    """ConfigError unless the `target` value `given` names ENVISAT: the detector and the verbs built on it (track,
    run, adapt, train, detect) know ENVISAT only."""
    if given != ENVISAT_TARGET and not load_target(given, field).is_envisat:
        raise ConfigError(field, given, _only_envisat(verb))


def require_envisat_truth(config: dict, field: str, given: str, verb: str) -> None:
    """ConfigError unless a truth file's config (TruthTrajectory.config, `given` its path) shows ENVISAT: the
    filter's measurement model holds ENVISAT's corners A-H, so another target's truth would be estimated with the
    wrong body (a confident wrong answer)."""
    target = (config.get("target") or {}).get("file", ENVISAT_TARGET)
    if target == ENVISAT_TARGET:
        return
    try:
        if load_target(target, field).is_envisat:
            return
    except ConfigError:
        pass
    raise ConfigError(field, given, f"a truth of ENVISAT ({ENVISAT_TARGET}): `envisat {verb}`'s filter measures "
                      f"ENVISAT's corners A-H only; this truth's target is {target!r}")


def require_envisat_dataset(folder: str, field: str, verb: str) -> None:
    """ConfigError unless the dataset in `folder` (its manifest.json) shows ENVISAT: its config's `target` is
    ENVISAT's (a dataset written before targets had none: ENVISAT). A folder without a manifest passes (the verb
    reports it)."""
    import json

    try:
        with open(os.path.join(folder, "manifest.json"), encoding="utf-8") as fh:
            manifest = json.load(fh)
    except (OSError, ValueError):
        return
    record = manifest.get("target") or {}
    given = (manifest.get("config") or {}).get("target", ENVISAT_TARGET)
    if given != ENVISAT_TARGET and (record.get("name") != "envisat" or
                                    record.get("keypoint_names") != list(CORNER_NAMES)):
        raise ConfigError(field, folder, _only_envisat(verb) + f"; this dataset's target is {given!r}")
