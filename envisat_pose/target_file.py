"""Reading a target file as MuJoCo reads it alone (envisat_pose.target builds the `Target` from what this returns).

The file is parsed by MuJoCo (MjSpec), so its own <compiler> (angle unit, eulerseq, meshdir, texturedir), defaults,
includes and assets apply; its body `target` is checked for structure (read_spec). A body with child bodies or
joints is read fused, its joints latched (target_fused.py); its files and sha256 are target_assets.py's.
"""

from __future__ import annotations

import numpy as np

from envisat_pose.config import ConfigError
from envisat_pose.geometry import CAMERA_NAME
from envisat_pose.target_assets import absolute_asset_files
from envisat_pose.target_fused import drop_lights, fused_text, subtree_bodies, tree_joints, unpin


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


def passed_over_sites(model, body: int, prefixes: tuple[str, ...], chosen: tuple[str, ...]) -> list[str]:
    """The sites of body id `body` named with a later prefix of `prefixes` than the one keypoint_sites chose for
    the `chosen` site names (a file with kp_ sites takes those alone: its corner_ sites are no keypoints)."""
    if not chosen:
        return []
    later = prefixes[prefixes.index(next(p for p in prefixes if chosen[0].startswith(p))) + 1:]
    sites = [model.site(s).name for s in range(model.nsite) if model.site_bodyid[s] == body]
    return [n for n in sites if n not in chosen and n.startswith(later)] if later else []


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

