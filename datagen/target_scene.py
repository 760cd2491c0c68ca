"""The factory's scene with a target in it (envisat_pose.target reads the target file).

A file that holds the factory's camera (models/envisat.xml) is its own scene, rendered as it is. Any other target
file's body `target` goes into ENVISAT's scene in place of ENVISAT's body, attached by MuJoCo itself (MjSpec):
the target file's own <compiler> (angle unit, eulerseq, meshdir, texturedir), defaults and assets apply to its
body as they do to the file alone, so the body has the shape MuJoCo gives the file. The scene adds the free joint
`target_free` and the relative-gravity plugin; the chaser and its camera, the clipping planes and the sun are the
same for every target; the renderer adds the Earth. The target's assets carry the prefix `target/` (no clash with
the scene's own); its body, geoms and sites keep their names.
"""

from __future__ import annotations

import functools
import os
import xml.etree.ElementTree as ET
from dataclasses import dataclass

from envisat_pose.geometry import model_path
from envisat_pose.target import Target, compiled_alone, load_target

ASSET_PREFIX = "target/"
SCENE_TARGET_POS_M = (0.0, 50.0, 0.0)  # where the scene's target body starts (the sim sets its state)


def _absolute_files(spec, folder: str) -> None:
    """Make the files of a spec's meshes, textures and height fields absolute (relative to the file's folder and
    its compiler's meshdir/texturedir), so the scene compiles from anywhere."""
    for kind, sub in (("meshes", spec.meshdir), ("hfields", spec.meshdir), ("textures", spec.texturedir)):
        for asset in getattr(spec, kind):
            if asset.file and not os.path.isabs(asset.file):
                asset.file = os.path.normpath(os.path.join(folder, sub or "", asset.file))


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
    child = mujoco.MjSpec.from_file(target.path)
    _absolute_files(child, os.path.dirname(target.path))
    frame = scene.worldbody.add_frame(pos=list(SCENE_TARGET_POS_M))
    body = frame.attach_body(child.body("target"), ASSET_PREFIX, "")
    body.name = "target"
    body.pos, body.quat = [0.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0]
    for i, geom in enumerate(body.geoms):  # looks and masks address geoms by name
        geom.name = target.geoms[i].name
    for site in body.sites:
        site.name = site.name.removeprefix(ASSET_PREFIX)
    body.add_freejoint(name="target_free")
    body.plugin.name, body.plugin.active = plugin[0], True
    return scene


_SIZE_NUMBERS = {"sphere": 1, "capsule": 2, "cylinder": 2, "box": 3, "ellipsoid": 3}


def _numbers(v) -> str:
    return " ".join(repr(float(x)) for x in v)


def full_precision(text: str, target: Target) -> str:
    """The scene text with the target body's numbers as the file alone compiles them, to the last bit: MuJoCo's
    to_xml writes 6 significant digits (an inertia 1e-6 off turns a tumble 2e-5 rad away in 30 minutes; a site
    3 um off). The inertial becomes its full tensor in T, each site its position and orientation, each primitive
    geom its position, orientation and size (a fromto resolved); a mesh geom keeps what MuJoCo wrote (its
    compiled pose holds the mesh's own centring, which the scene applies again)."""
    root = ET.fromstring(text)
    body = next(b for b in root.iter("body") if b.get("name") == "target")
    alone = compiled_alone(target)
    own = alone.body("target").id
    J = target.inertia_T_kg_m2
    inertial = body.find("inertial")
    inertial.attrib.clear()
    inertial.attrib.update({"pos": "0 0 0", "mass": repr(target.mass_kg), "fullinertia": _numbers(
        [J[0, 0], J[1, 1], J[2, 2], J[0, 1], J[0, 2], J[1, 2]])})
    sites = [s for s in range(alone.nsite) if alone.site_bodyid[s] == own]
    for el, s in zip(body.findall("site"), sites):
        el.set("pos", _numbers(alone.site_pos[s]))
        el.set("quat", _numbers(alone.site_quat[s]))
    geoms = [g for g in range(alone.ngeom) if alone.geom_bodyid[g] == own]
    for el, g, info in zip(body.findall("geom"), geoms, target.geoms):
        if info.type not in _SIZE_NUMBERS:
            continue
        for key in ("fromto", "euler", "axisangle", "xyaxes", "zaxis"):
            el.attrib.pop(key, None)
        el.set("pos", _numbers(alone.geom_pos[g]))
        el.set("quat", _numbers(alone.geom_quat[g]))
        el.set("size", _numbers(alone.geom_size[g][:_SIZE_NUMBERS[info.type]]))
    return ET.tostring(root, encoding="unicode")


@functools.lru_cache(maxsize=16)
def _scene_text(path: str, sha256: str, own_scene: bool) -> str:
    if own_scene:
        with open(path, encoding="utf-8") as fh:
            return fh.read()
    target = load_target(path)
    return full_precision(_scene_spec(target).to_xml(), target)


def scene_xml(target: Target) -> str:
    """The MJCF text of the factory's scene with `target` in it (a file that is its own scene: as it is).
    MuJoCo writes the attached body in its compiled terms: quaternions (to 6 digits), defaults resolved."""
    return _scene_text(target.path, target.sha256, target.own_scene)


@dataclass(frozen=True)
class TargetScene:
    """What the factory needs of a target's scene without GL: geom_names (G,) of body 'target' in file order;
    mask_values {geom: 1..G} (a file that names its geoms after the factory's classes: render.MASK_VALUES);
    base_rgb {geom: (3,)} of each geom's material (or its own rgba), the colour another target's looks vary."""

    geom_names: tuple[str, ...]
    mask_values: dict
    base_rgb: dict


def target_scene(target: Target) -> TargetScene:
    """The TargetScene of a target, from its Target."""
    names = tuple(g.name for g in target.geoms)
    return TargetScene(names, {name: min(i + 1, 255) for i, name in enumerate(names)},
                       {g.name: g.rgb for g in target.geoms})
