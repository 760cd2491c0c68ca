"""A target file's body `target` tree fused into one body, written back as MJCF (target_file.read_spec reads it).

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
import os
import xml.etree.ElementTree as ET

import numpy as np

from envisat_pose.attitude import quat_to_rotmat
from envisat_pose.target_assets import absolute_asset_files

PRIMITIVE_SIZES = {"sphere": 1, "capsule": 2, "cylinder": 2, "box": 3, "ellipsoid": 3}  # numbers in a geom's size
_ORIENTATIONS = ("quat", "euler", "axisangle", "xyaxes", "zaxis")
_UNNAMED = "__fused_"  # the prefix of the names given for the fusing to the unnamed


def full_numbers(v) -> str:
    """Numbers as MJCF text to the last bit (repr of each float)."""
    return " ".join(repr(float(x)) for x in v)


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

