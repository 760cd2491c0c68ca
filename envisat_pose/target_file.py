"""Reading a target file as MuJoCo reads it alone (envisat_pose.target builds the `Target` from what this returns).

The file is parsed by MuJoCo (MjSpec), so its own <compiler> (angle unit, eulerseq, meshdir, texturedir), defaults,
includes and assets apply; its body `target` is checked for structure (read_spec).

A spacecraft is often written as a tree: a bus with its wings, antennas and booms as child bodies (or MJCF <frame>
elements: the same, without masses of their own). Without joints the tree is one rigid body, and MuJoCo says so
itself: its compiler's `fusestatic` moves every geom and site of a static child into the parent, the child's pose
composed, and sums the masses and inertias about the common centre of mass. That is done here once, to the file
alone (the body given a free joint for the compile, so that it is not fused into the world), and written back as a
file whose body `target` holds everything directly (fused_text): its inertial the composite one and its sites and
geoms at their compiled poses in T, to the last bit (a mesh geom's less its own centring, which compiling the text
applies again). Keypoints keep MuJoCo's order: the body's own sites, then each child's, depth first. A joint
anywhere in the tree (a <freejoint/> on the body, a hinge deploying a wing) is latched: the target is one rigid
body at the file's reference configuration (every joint at qpos0, where MuJoCo draws the bodies as written), the
joint taken out and with it what only a mechanism needs (actuators, tendons, equalities, sensors, contact pairs and
exclusions, keyframes); the scene adds its own free joint. Lights on the target are taken out (drop_lights): the
factory's scene lights it.
"""

from __future__ import annotations

import functools
import hashlib
import os
import re
import xml.etree.ElementTree as ET

import numpy as np

from envisat_pose.attitude import quat_to_rotmat
from envisat_pose.config import ConfigError
from envisat_pose.geometry import CAMERA_NAME

PRIMITIVE_SIZES = {"sphere": 1, "capsule": 2, "cylinder": 2, "box": 3, "ellipsoid": 3}  # numbers in a geom's size
_ORIENTATIONS = ("quat", "euler", "axisangle", "xyaxes", "zaxis")
_UNNAMED = "__fused_"  # the prefix of the names given for the fusing to the unnamed


def full_numbers(v) -> str:
    """Numbers as MJCF text to the last bit (repr of each float)."""
    return " ".join(repr(float(x)) for x in v)


ASSET_FOLDERS = (("meshes", "meshdir"), ("hfields", "meshdir"), ("skins", "meshdir"), ("textures", "texturedir"))


def _absolute(name: str, folder: str, sub: str) -> str:
    return name if not name or os.path.isabs(name) else os.path.normpath(os.path.join(folder, sub or "", name))


def absolute_asset_files(spec, path: str) -> None:
    """Make the files of a spec's meshes, height fields, skins and textures (a cube's six faces too) absolute
    (relative to the folder of the file at `path` and its compiler's meshdir/texturedir; an asset of a model the
    file attaches (<attach model=...>) relative to that model's file and its compiler: attached_assets), so the
    spec compiles from anywhere."""
    folder = os.path.dirname(path)
    attached = attached_assets(path)
    for kind, sub in ASSET_FOLDERS:
        for asset in getattr(spec, kind):
            if (kind, asset.name) in attached:
                asset.file, cubefiles = attached[(kind, asset.name)]
                if any(cubefiles):
                    asset.cubefiles = list(cubefiles)
                continue
            asset.file = _absolute(asset.file, folder, getattr(spec, sub))
            if kind == "textures" and any(asset.cubefiles):
                asset.cubefiles = [_absolute(f, folder, spec.texturedir) for f in asset.cubefiles]


def attached_models(path: str) -> list[tuple[str, str]]:
    """(absolute file, prefix) of each model the MJCF file at `path` attaches (<attach model=... prefix=...>, its
    <model name=... file=...> relative to the file's folder; either may be in a file it includes), in file order;
    unreadable files skipped (MuJoCo's reading reports them)."""
    folder = os.path.dirname(path)
    models, attaches = {}, []
    for name in [path, *_included_files(path, folder)]:
        try:
            root = ET.parse(name).getroot()
        except (OSError, ET.ParseError):
            continue
        models.update({el.get("name"): os.path.normpath(os.path.join(folder, el.get("file", "")))
                       for el in root.iter("model") if el.get("file")})
        attaches += [(el.get("model"), el.get("prefix", "")) for el in root.iter("attach")]
    return [(models[m], prefix) for m, prefix in attaches if m in models and os.path.isfile(models[m])]


def attached_assets(path: str) -> dict[tuple[str, str], tuple[str, tuple[str, ...]]]:
    """{(kind, name in the attaching spec): (absolute file, absolute cube files)} of the assets of the models the
    file at `path` attaches (attached_models), theirs too: MuJoCo reads an attached model's asset files relative to
    that model's own file and compiler (meshdir, texturedir), which its spec keeps from no one (to_xml writes the
    bare names). Names carry the attach's prefix, as MuJoCo gives them."""
    import mujoco

    out: dict[tuple[str, str], tuple[str, tuple[str, ...]]] = {}
    for file, prefix in attached_models(path):
        try:
            child = mujoco.MjSpec.from_file(file)
        except ValueError:
            continue  # MuJoCo's reading of the attaching file reports it
        absolute_asset_files(child, file)
        for kind, _ in ASSET_FOLDERS:
            for asset in getattr(child, kind):
                out[(kind, prefix + asset.name)] = (asset.file, tuple(getattr(asset, "cubefiles", ())))
    return out


def asset_files(spec) -> set[str]:
    """Every file a spec's assets name (after absolute_asset_files: absolute), a cube texture's faces included."""
    named = {a.file for kind, _ in ASSET_FOLDERS for a in getattr(spec, kind)}
    named |= {f for t in spec.textures for f in t.cubefiles}
    return {f for f in named if f}


def subtree_bodies(body) -> list:
    """The bodies below `body` (an MjsBody, or a spec's worldbody), depth first."""
    out = []
    for child in body.bodies:
        out += [child, *subtree_bodies(child)]
    return out


def _quat_mul(a: np.ndarray, b: np.ndarray, conjugate_b: bool = False) -> np.ndarray:
    """MuJoCo's quaternion product a b (or a b* with conjugate_b), (w, x, y, z)."""
    import mujoco

    b = np.asarray(b, float)
    if conjugate_b:
        b_conj = np.zeros(4)
        mujoco.mju_negQuat(b_conj, b)
        b = b_conj
    out = np.zeros(4)
    mujoco.mju_mulQuat(out, np.asarray(a, float), b)
    return out


def set_compiled_geom(el: ET.Element, model, g: int) -> None:
    """Write geom g's compiled numbers into its MJCF element el, to the last bit: a primitive's pose and size in
    its body (a fromto or another orientation form dropped); a mesh's pose as written, i.e. the compiled one less
    the mesh's own centring (mesh_pos, mesh_quat), which compiling the text applies again. Other types untouched."""
    import mujoco

    kind = mujoco.mjtGeom(int(model.geom_type[g])).name.removeprefix("mjGEOM_").lower()
    pos, quat = np.asarray(model.geom_pos[g], float), np.asarray(model.geom_quat[g], float)
    if kind == "mesh":
        m = int(model.geom_dataid[g])
        quat = _quat_mul(quat, model.mesh_quat[m], conjugate_b=True)
        pos = pos - quat_to_rotmat(quat) @ np.asarray(model.mesh_pos[m], float)
    elif kind not in PRIMITIVE_SIZES:
        return
    for key in (*_ORIENTATIONS, "fromto"):
        el.attrib.pop(key, None)
    el.set("pos", full_numbers(pos))
    el.set("quat", full_numbers(quat))
    if kind != "mesh":
        el.set("size", full_numbers(model.geom_size[g][:PRIMITIVE_SIZES[kind]]))


def set_compiled_site(el: ET.Element, model, s: int) -> None:
    """Write site s's compiled pose in its body into its MJCF element el, to the last bit."""
    for key in _ORIENTATIONS:
        el.attrib.pop(key, None)
    el.set("pos", full_numbers(model.site_pos[s]))
    el.set("quat", full_numbers(model.site_quat[s]))


def _pose(el: ET.Element) -> tuple[np.ndarray, np.ndarray]:
    """The written pose (pos (3,), quat (4,)) of an element MuJoCo's to_xml wrote (quaternions only)."""
    pos = np.array([float(v) for v in el.get("pos", "0 0 0").split()])
    quat = np.array([float(v) for v in el.get("quat", "1 0 0 0").split()])
    return pos, quat / np.linalg.norm(quat)


def _dissolve_frames(parent: ET.Element, pos: np.ndarray, quat: np.ndarray, into: list[ET.Element],
                     childclass: str | None = None) -> None:
    """Every child of parent (a frame at pose (pos, quat) in T, or the body itself at the identity) into `into`,
    in document order, nested frames dissolved, each element's written pose composed with its frames' and its
    default class the innermost frame's childclass where it names none itself (as MuJoCo reads a frame)."""
    R = quat_to_rotmat(quat)
    for el in list(parent):
        p, q = _pose(el)
        p_T, q_T = pos + R @ p, _quat_mul(quat, q)
        if el.tag == "frame":
            _dissolve_frames(el, p_T, q_T, into, el.get("childclass", childclass))
            continue
        if parent.tag == "frame":
            for key in _ORIENTATIONS:
                el.attrib.pop(key, None)
            el.set("pos", full_numbers(p_T))
            el.set("quat", full_numbers(q_T))
            if childclass is not None and "class" not in el.attrib:
                el.set("class", childclass)
        into.append(el)


def fused_text(path: str) -> str | None:
    """The file at `path` as MuJoCo's fusestatic leaves it, written as a file whose body `target` holds every geom
    and site directly, its joints latched (module docstring); None where that body has no child bodies, no frames
    and no joints (the file is read as it is). ValueError where MuJoCo does not compile it."""
    return _fused_text(path, os.stat(path).st_mtime_ns)


MECHANISM_KINDS = ("actuators", "tendons", "equalities", "sensors", "pairs", "excludes", "keys")  # what joints drive


def tree_joints(body) -> list:
    """The joints of body `target` (an MjsBody) and of its child bodies, depth first."""
    return [j for b in [body, *subtree_bodies(body)] for j in b.joints]


def latch_joints(spec) -> None:
    """Take the joints of spec's body `target` and its child bodies out, and the file's mechanism with them
    (MECHANISM_KINDS: what may name a joint), so the tree compiles as one rigid body at its reference pose."""
    joints = tree_joints(spec.body("target"))
    if not joints:
        return
    for kind in MECHANISM_KINDS:
        for el in list(getattr(spec, kind)):
            spec.delete(el)
    for j in joints:
        spec.delete(j)


def unpin(spec) -> None:
    """Clear the mocap flag of spec's body `target`: a body a viewer moves by hand (mocap="true") is, alone, drawn
    where it is written, and the target is one free rigid body (the fusing and the scene give it a free joint,
    which MuJoCo refuses a mocap body)."""
    spec.body("target").mocap = False


def drop_lights(spec) -> None:
    """Take the lights of spec's body `target` and its child bodies (a <frame>'s too) out: the factory's scene
    lights the target (its sun, the Earth-shine), not the file, and a light's `dir` has no place in a fused file."""
    for b in [spec.body("target"), *subtree_bodies(spec.body("target"))]:
        for light in list(b.lights):
            spec.delete(light)


@functools.lru_cache(maxsize=16)
def _fused_text(path: str, mtime_ns: int) -> str | None:
    import mujoco

    spec = mujoco.MjSpec.from_file(path)
    target = spec.body("target")
    if target is None or not (target.bodies or target.frames or tree_joints(target)):
        return None
    latch_joints(spec)
    drop_lights(spec)
    unpin(spec)
    absolute_asset_files(spec, path)
    tree = [target, *subtree_bodies(target)]
    for b in subtree_bodies(spec.worldbody):
        b.fuse = b in tree  # the file's other bodies stay as they are
    for kind in ("geoms", "sites"):  # every element named, so the written ones are found again in the compiled model
        for k, el in enumerate(el for b in tree for el in getattr(b, kind)):
            el.name = el.name or f"{_UNNAMED}{kind}_{k}"
    target.add_freejoint(name=f"{_UNNAMED}free")
    spec.compiler.fusestatic = True
    model = spec.compile()
    root = ET.fromstring(spec.to_xml())
    body = next(b for b in root.iter("body") if b.get("name") == "target")
    elements: list[ET.Element] = []
    _dissolve_frames(body, np.zeros(3), np.array([1.0, 0.0, 0.0, 0.0]), elements)
    for el in list(body):
        body.remove(el)
    b = model.body("target").id
    ET.SubElement(body, "inertial", {  # the composite one, at the compiled numbers
        "pos": full_numbers(model.body_ipos[b]), "quat": full_numbers(model.body_iquat[b]),
        "mass": repr(float(model.body_mass[b])), "diaginertia": full_numbers(model.body_inertia[b])})
    geoms = sorted((model.geom(el.get("name")).id, el) for el in elements if el.tag == "geom")
    sites = sorted((model.site(el.get("name")).id, el) for el in elements if el.tag == "site")
    for g, el in geoms:  # in MuJoCo's order (to_xml writes a frame's elements after the body's own)
        set_compiled_geom(el, model, g)
    for s_id, el in sites:
        set_compiled_site(el, model, s_id)
    rest = [el for el in elements if el.tag not in ("geom", "site", "inertial", "joint", "freejoint")]
    for el in [el for _, el in geoms] + [el for _, el in sites] + rest:
        if el.get("name", "").startswith(_UNNAMED):
            del el.attrib["name"]
        body.append(el)
    return ET.tostring(root, encoding="unicode")


def keypoint_sites(model, body: int, prefixes: tuple[str, ...]) -> tuple[tuple[str, ...], tuple[str, ...], np.ndarray]:
    """(names, site names, (K, 3) positions in T) of the sites of body id `body` of a compiled model named with the
    first of `prefixes` any of them has (a target's kp_ sites, else its corner_ sites); names: after the prefix."""
    sites = [s for s in range(model.nsite) if model.site_bodyid[s] == body]
    for prefix in prefixes:
        chosen = [s for s in sites if model.site(s).name.startswith(prefix)]
        if chosen:
            return (tuple(model.site(s).name[len(prefix):] for s in chosen), tuple(model.site(s).name for s in chosen),
                    np.array([model.site_pos[s] for s in chosen], float))
    return (), (), np.zeros((0, 3))


def misprefixed_keypoints(model, body: int, prefix: str) -> str:
    """A hint for a refusal that found too few keypoints on body id `body` of a compiled model: the sites whose
    names hold the keypoint prefix further in (an <attach prefix=...> put before a model's kp_ sites, which then
    are not keypoints), else its other sites (a prefix misspelt), or '' where it has none."""
    sites = [model.site(s).name for s in range(model.nsite) if model.site_bodyid[s] == body]
    named = [n for n in sites if prefix in n and not n.startswith(prefix)]
    if not named:  # the body's other sites, by name (KP_A, kp-a, a): a keypoint's name starts with the prefix
        other = [repr(n) if n else "an unnamed one" for n in sites if not n.startswith(prefix)]
        return (f"; not keypoints: its site(s) {', '.join(other[:6])}{', ...' if len(other) > 6 else ''}, whose "
                f"names do not start with {prefix!r} (case matters)" if other else "")
    shown = ", ".join(repr(n) for n in named[:3]) + (", ..." if len(named) > 3 else "")
    return (f"; {len(named)} site(s) hold {prefix!r} after another prefix ({shown}): a keypoint's site name starts "
            f"with it, so an <attach prefix> before keypoint sites should itself start with {prefix!r}")


def drawn_alpha(model, g: int) -> float:
    """The alpha MuJoCo's renderer draws geom g of `model` with: its own rgba's where that rgba is not MuJoCo's
    default (0.5 0.5 0.5 1: then it overrides the material's), else its material's, else its own."""
    mat = int(model.geom_matid[g])
    own = model.geom_rgba[g]
    overrides = mat < 0 or not np.array_equal(own, np.array([0.5, 0.5, 0.5, 1.0], np.float32))
    return float(own[3] if overrides else model.mat_rgba[mat][3])


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


def _spec_inertia(body) -> np.ndarray:
    """The inertia a body's <inertial> states, in its principal or full form (orientation aside: the checks read
    only its eigenvalues)."""
    full = np.asarray(body.fullinertia, float)
    if not np.isnan(full[0]):
        xx, yy, zz, xy, xz, yz = full
        return np.array([[xx, xy, xz], [xy, yy, yz], [xz, yz, zz]])
    return np.diag(np.asarray(body.inertia, float))


UNREAD_GEOMS = {"plane": "a plane, which MuJoCo allows only in the world's static bodies: a panel is a thin box",
                "hfield": "a height field, whose surface the labels' visibility cannot read: write it as a mesh",
                "sdf": "a signed distance field, whose surface the labels' visibility cannot read: write it as a mesh"}


def unread_geom(body) -> str | None:
    """What a target refuses of the geoms of `body` (an MjsBody of its tree), or None: a plane, a height field or
    an SDF (UNREAD_GEOMS), named by its name or its number in the body's file order."""
    for k, g in enumerate(body.geoms):
        kind = str(g.type).rsplit(".", 1)[-1].removeprefix("mjGEOM_").lower()
        if kind in UNREAD_GEOMS:
            named = repr(g.name) if g.name else f"number {k + 1}"
            return (f"geoms of box, sphere, capsule, cylinder, ellipsoid or mesh type on body {body.name!r} "
                    f"(its geom {named} is {UNREAD_GEOMS[kind]})")
    return None


def inertial_used(spec, body) -> bool:
    """Whether MuJoCo takes body's mass properties from its <inertial>: one is written and the compiler's
    inertiafromgeom is not 'true' (which computes them from the geoms whatever the file states)."""
    import mujoco

    from_geoms = spec.compiler.inertiafromgeom == mujoco.mjtInertiaFromGeom.mjINERTIAFROMGEOM_TRUE
    return bool(body.explicitinertial) and not from_geoms


# what the factory addresses by name in the scene models/envisat.xml holds (datagen/render.py and sim.py; render_model
# adds the Earth): a file holding all of them is its own scene
SCENE_NAMES = (("camera", CAMERA_NAME), ("body", "chaser"), ("joint", "target_free"), ("light", "sun"))


def read_spec(path: str, field: str, given: str):
    """MuJoCo's reading of the file (its own compiler settings) with its body `target` checked for structure:
    (spec, own_scene, fused, latched). A body with child bodies or joints is read fused (fused: True), its joints
    latched (fused_text); latched: those joints' names (an unnamed one as '<kind> joint of body NAME'); own_scene: the
    file holds every name the factory's scene is addressed by (SCENE_NAMES: models/envisat.xml, a copy of it), so it
    is its own scene; the file's <statistic> set aside (the spec compiles MuJoCo's own extent and centre).
    ConfigError naming `field` and the
    value `given` otherwise: a file MuJoCo cannot read, no body 'target', a bad <inertial>, a scene file whose
    target has child bodies."""
    import mujoco

    def fail(expected: str):
        raise ConfigError(field, given, expected)

    try:
        spec = mujoco.MjSpec.from_file(path)
    except ValueError as err:
        fail(f"an MJCF file MuJoCo reads (it says: {' '.join(str(err).split())})")
    body = spec.body("target")
    if body is None:
        fail("an MJCF file whose worldbody holds a body named 'target'")
    own_scene = all(getattr(spec, kind)(name) is not None for kind, name in SCENE_NAMES)  # models/envisat.xml, a copy
    tree = subtree_bodies(body)
    if own_scene and tree:
        fail("a scene file whose body 'target' has no child bodies")
    joints = [] if own_scene else tree_joints(body)  # a scene file holds the scene's own free joint
    latched = tuple(j.name or f"{str(j.type).rsplit('.', 1)[-1].removeprefix('mjJNT_').lower()} joint of body "
                    f"{j.parent.name!r}" for j in joints)
    for b in [body, *tree]:
        problem = unread_geom(b)
        if problem is not None:
            fail(problem)
        if inertial_used(spec, b) and not spec.compiler.balanceinertia:  # else MuJoCo's (checked once compiled)
            problem = check_inertia(float(b.mass), _spec_inertia(b))
            if problem is not None:
                fail(f"body {b.name or 'target'!r} with {problem}")
    if tree or joints:
        try:
            spec = mujoco.MjSpec.from_string(fused_text(path))
        except ValueError as err:
            fail(f"an MJCF file MuJoCo compiles (it says: {' '.join(str(err).split())})")
    spec.stat.extent, spec.stat.center = float("nan"), [float("nan"), 0.0, 0.0]  # MuJoCo's own, from the geometry:
    # a file's <statistic extent> (a viewer's setting) would set the centre of mass's tolerance (a share of it)
    return spec, own_scene, bool(tree or joints), latched


def compile_alone(path: str):
    """The target file compiled alone, as the Target reads it (fused where its body has child bodies): MjModel."""
    import mujoco

    text = fused_text(path)
    return mujoco.MjModel.from_xml_path(path) if text is None else mujoco.MjModel.from_xml_string(text)


def target_spec(path: str):
    """The target file's MjSpec as the factory's scene takes it (fused where its body has child bodies), its asset
    files absolute, its lights out (drop_lights)."""
    import mujoco

    text = fused_text(path)
    spec = mujoco.MjSpec.from_file(path) if text is None else mujoco.MjSpec.from_string(text)
    drop_lights(spec)
    unpin(spec)
    absolute_asset_files(spec, path)
    return spec


def _included_files(path: str, base: str) -> list[str]:
    """The files the MJCF file at `path` includes (<include file=...>, relative to the main file's folder base),
    and theirs, depth first; unreadable ones skipped (MuJoCo's reading reports them)."""
    try:
        root = ET.parse(path).getroot()
    except (OSError, ET.ParseError):
        return []
    out = []
    for el in root.iter("include"):
        name = os.path.normpath(os.path.join(base, el.get("file", "")))
        if os.path.isfile(name):
            out += [name, *_included_files(name, base)]
    return out


def named_files(path: str) -> tuple[str, ...]:
    """The files the target file at `path` names (includes, attached models, meshes, textures, height fields),
    absolute, sorted; none where no 'file...=' is in it (the shipped targets). Cached per file and modification
    time."""
    return _named_files(path, os.stat(path).st_mtime_ns)


@functools.lru_cache(maxsize=16)
def _named_files(path: str, mtime_ns: int) -> tuple[str, ...]:
    with open(path, "rb") as fh:
        if not re.search(rb"file[a-z]*\s*=", fh.read()):  # file=, or a cube texture's fileright= ...
            return ()
    import mujoco

    folder = os.path.dirname(path)
    named = set(_included_files(path, folder))
    for model, _ in attached_models(path):  # an attached model's file and those it names (its includes, models)
        named |= {model, *named_files(model)}
    try:
        spec = mujoco.MjSpec.from_file(path)
        absolute_asset_files(spec, path)
        named |= asset_files(spec)
    except ValueError:
        pass  # MuJoCo's reading reports it
    return tuple(sorted(named))


def target_sha256(path: str) -> str:
    """What identifies a target: the sha256 of its file's bytes and of each file it names (named_files: an edited
    mesh is another target), named relative to the file's folder. A file that names none hashes as its bytes."""
    with open(path, "rb") as fh:
        digest = hashlib.sha256(fh.read())
    for name in named_files(path):
        try:
            with open(name, "rb") as fh:
                body = fh.read()
        except OSError:
            continue  # MuJoCo's reading reports it
        digest.update(b"\0" + os.path.relpath(name, os.path.dirname(path)).encode() + b"\0" + body)
    return digest.hexdigest()
