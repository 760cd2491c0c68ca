"""The project's MJCF prepared for rendering (render_model_xml): the off-screen buffer, the fixed model extent, the
Earth backdrop body and its textures' slots, the Earth-shine light and the appearance materials of
appearance randomization, edited in memory (models/envisat.xml is not changed)."""

from __future__ import annotations

# MuJoCo picks its GL platform at import: gl_platform chooses a headless one before mujoco loads.
from envisat_pose.datagen import gl_platform  # noqa: F401

# isort: split

import xml.etree.ElementTree as ET

import mujoco

from envisat_pose.datagen.appearance import (
    CLASSES,
    FACE_GEOMS,
    GEOM_CLASS,
    OWN_CLASS,
    TEXTURE_PX,
    takes_class_appearance,
)
from envisat_pose.datagen.earth import (
    EARTH_MESH_STEPS_DEG,
    EARTH_SCALE,
    EARTH_TEXTURE_SET_SIZE,
    cap_mesh_xml_attributes,
    earth_texture_width,
    mesh_xml_attributes,
)
from envisat_pose.datagen.scenario import EARTH_RADIUS_M
from envisat_pose.geometry import model_path

EARTH_GEOM_GROUP = 5  # hidden unless a view asks for the backdrop
EARTH_ALPHA = 0.99  # the Earth's material alpha (see render_model_xml); its texture is scaled up to match
HIDDEN_SITE_GROUP = 5  # every site's group here: sites are labels, never drawn (MuJoCo draws site groups 0-2)


def render_model_xml(resolution_px: int, base_xml: str | None = None, texture_set_size: int = 0,
                     earth_texture_set_size: int = EARTH_TEXTURE_SET_SIZE) -> str:
    """The project's MJCF prepared for rendering at `resolution_px`: a large enough off-screen buffer, a fixed
    model extent (the far plane and shadow box stay those of models/envisat.xml; another target's near plane is
    sized to it, target_scene), an Earth backdrop body (mocap, geom group 5, hidden by default: a unit UV-sphere mesh scaled to EARTH_RADIUS_M x EARTH_SCALE,
    `earth_texture_set_size` equirectangular textures, their pixels written by the renderer), an Earth-shine
    light (off until an appearance turns it on), every site out of the drawn groups (HIDDEN_SITE_GROUP), and
    for appearance randomization `texture_set_size` textures per covering class with one material
    `appearance_<geom>_<class>_<k>` per target geom, class and texture (texture pixels are written by the renderer).

    The XML tree is edited in memory; models/envisat.xml is not changed.
    """
    text = base_xml if base_xml is not None else open(model_path(), encoding="utf-8").read()
    base = mujoco.MjModel.from_xml_string(text)
    root = ET.fromstring(text)
    visual = root.find("visual")
    if visual is None:
        visual = ET.SubElement(root, "visual")
    glob = visual.find("global")
    if glob is None:
        glob = ET.SubElement(visual, "global")
    glob.set("offwidth", str(max(resolution_px, int(base.vis.global_.offwidth))))
    glob.set("offheight", str(max(resolution_px, int(base.vis.global_.offheight))))
    stat = root.find("statistic")
    if stat is None:
        stat = ET.SubElement(root, "statistic")
    stat.set("extent", repr(float(base.stat.extent)))
    stat.set("center", " ".join(repr(float(v)) for v in base.stat.center))
    asset = root.find("asset")
    if asset is None:
        asset = ET.SubElement(root, "asset")
    ET.SubElement(asset, "material", name="earth_backdrop", rgba="0.35 0.42 0.55 1", specular="0.05",
                  shininess="0.05", reflectance="0")
    w = earth_texture_width(resolution_px)
    for k in range(earth_texture_set_size):
        # the globe (equirectangular) and the detailed cap a low orbit sees (earth.earth_cap_texture)
        for kind, height in (("earth", w // 2), ("earth_cap", w)):
            ET.SubElement(asset, "texture", name=f"{kind}_tex_{k}", type="2d", builtin="flat", width=str(w),
                          height=str(height), rgb1="0.3 0.3 0.3")
            # alpha just below 1: the Earth is drawn in mjr_render's transparent pass (once, additively over the
            # black sky, lit by every light, receiving no shadow), not twice as opaque geoms with a shadow light
            ET.SubElement(asset, "material", name=f"{kind}_{k}", texture=f"{kind}_tex_{k}",
                          rgba=f"1 1 1 {EARTH_ALPHA}", specular="0.03", shininess="0.1", reflectance="0")
    scale = repr(EARTH_RADIUS_M * EARTH_SCALE)
    for step in EARTH_MESH_STEPS_DEG:  # levels of detail; the view picks one (earth.mesh_step_for)
        ET.SubElement(asset, "mesh", name=f"earth_sphere_{step:g}", scale=f"{scale} {scale} {scale}",
                      **mesh_xml_attributes(step))
    ET.SubElement(asset, "mesh", name="earth_cap", scale=f"{scale} {scale} {scale}", **cap_mesh_xml_attributes())
    world = root.find("worldbody")
    earth = ET.SubElement(world, "body", name="earth_backdrop", mocap="true", pos="0 0 -1e5")
    ET.SubElement(earth, "geom", name="earth_backdrop", type="mesh", mesh=f"earth_sphere_{EARTH_MESH_STEPS_DEG[0]:g}",
                  material="earth_0" if earth_texture_set_size else "earth_backdrop", group=str(EARTH_GEOM_GROUP),
                  contype="0", conaffinity="0")
    # Earth-shine: sunlight reflected by the Earth, a directional light from the nadir side, no shadows
    ET.SubElement(world, "light", name="earthshine", directional="true", castshadow="false", pos="0 0 100",
                  dir="0 0 -1", diffuse="0 0 0", specular="0 0 0", ambient="0 0 0", active="false")
    for site in world.iter("site"):  # a kp_ site of group 0 would show as MuJoCo's 5 mm ball on the keypoint
        site.set("group", str(HIDDEN_SITE_GROUP))
    body = next(b for b in world.iter("body") if b.get("name") == "target")
    own = not takes_class_appearance(g.get("name") for g in body.findall("geom"))  # its own materials, varied
    if texture_set_size > 0 and own:
        _own_appearance_materials(asset, body)
    elif texture_set_size > 0:
        for cls in sorted(CLASSES):
            for k in range(texture_set_size):
                ET.SubElement(asset, "texture", name=f"tex_{cls}_{k}", type="2d", builtin="flat",
                              width=str(TEXTURE_PX), height=str(TEXTURE_PX), rgb1="1 1 1")
        for geom, cls in GEOM_CLASS.items():
            for c in appearance_classes(geom):
                rep = repr(1.0 / CLASSES[c].tile_m)
                for k in range(texture_set_size):
                    ET.SubElement(asset, "material", name=f"appearance_{geom}_{c}_{k}", texture=f"tex_{c}_{k}",
                                  texuniform="true", texrepeat=f"{rep} {rep}")
    return ET.tostring(root, encoding="unicode")


def _own_appearance_materials(asset: ET.Element, body: ET.Element) -> None:
    """Another target's appearance: one material `appearance_<geom>_own_0` per geom of body `target`, a copy of
    the geom's own material (its texture kept; a geom without one gets its rgba), whose colour and specular terms
    an appearance writes (appearance.draw_own_materials)."""
    import copy

    materials = {m.get("name"): m for m in asset.findall("material")}
    for geom in body.findall("geom"):
        src = materials.get(geom.get("material", ""))
        mat = copy.deepcopy(src) if src is not None else ET.Element("material", rgba=geom.get("rgba", "0.5 0.5 0.5 1"))
        mat.set("name", f"appearance_{geom.get('name')}_{OWN_CLASS}_0")
        asset.append(mat)


def appearance_classes(geom: str) -> tuple[str, ...]:
    """The covering classes a geom's appearance may take: any for a face of the main body (AppearanceConfig's
    one_covering), its own class for every other geom."""
    return tuple(sorted(CLASSES)) if geom in FACE_GEOMS else (GEOM_CLASS[geom],)
