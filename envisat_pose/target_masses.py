"""What to do about a target file whose centre of mass is off the body's origin: the refusal's words.

A target written as a tree (envisat_pose/target_fused.py) has its mass summed over the body `target` and its child
bodies. A child body without an <inertial> takes its mass from its geoms, and a geom without `mass` takes its volume
times `density`, MuJoCo's 1000 kg/m^3 by default: a solar panel written as a child box weighs kilograms beside the
craft's own <inertial>, and the centre of mass leaves the origin. The refusal names each body's share (com_hint)
so the file's author sees which one moved it, and says what brings it back.
"""

from __future__ import annotations

import numpy as np

from envisat_pose.target_assets import absolute_asset_files
from envisat_pose.target_file import inertial_used
from envisat_pose.target_fused import drop_lights, latch_joints, subtree_bodies, unpin


def tree_masses(path: str) -> list[tuple[str, float, np.ndarray, bool]]:
    """Each body of the file's `target` tree, depth first, as MuJoCo compiles it unfused, joints latched: (name,
    mass kg, its centre of mass in T m, whether the mass is its <inertial>'s); [] where MuJoCo does not compile it
    so."""
    import mujoco

    try:
        spec = mujoco.MjSpec.from_file(path)
        latch_joints(spec)
        drop_lights(spec)
        unpin(spec)
        absolute_asset_files(spec, path)
        tree = [spec.body("target"), *subtree_bodies(spec.body("target"))]
        stated = [inertial_used(spec, b) for b in tree]
        names = [b.name for b in tree]
        for k, b in enumerate(tree):  # every body found again in the compiled model
            b.name = b.name or f"__tree_body_{k}"
        spec.body(tree[0].name).add_freejoint()
        spec.compiler.fusestatic = False
        model = spec.compile()
    except ValueError:
        return []
    data = mujoco.MjData(model)
    mujoco.mj_kinematics(model, data)
    root = model.body(tree[0].name).id
    R = data.xmat[root].reshape(3, 3)
    out = []
    for name, b, own in zip(names, tree, stated):
        i = model.body(b.name).id
        out.append((name, float(model.body_mass[i]), R.T @ (data.xipos[i] - data.xpos[root]), own))
    return out


def _vec(v: np.ndarray) -> str:
    return "[" + ", ".join(f"{x:.4g}" for x in np.where(np.abs(v) < 1e-9, 0.0, v)) + "]"


def frame_pos(com: np.ndarray) -> str:
    """The <frame> that moves what it wraps by -com (m; 9 significant digits, within the check's tolerance)."""
    return "<frame pos='" + " ".join(f"{0.0 if abs(x) < 1e-12 else -x:.9g}" for x in com) + "'>"


def com_hint(path: str, fused: bool, stated: bool, whose: str, com: np.ndarray) -> str:
    """The refusal's words after 'the centre of mass at the body's origin': where MuJoCo puts it, from what, and
    what brings it to the origin (each way to move the geometry: by hand, or wrapped in one <frame> inside body
    'target', frame_pos). `stated`: a flat body's <inertial> is used; `whose`: what the masses came from."""
    frame = frame_pos(com)
    if stated:
        return (f"<inertial pos='0 0 0'>, got {com.tolist()}: set it so, and move the geoms and sites by its "
                f"negative, or wrap them in {frame} inside body 'target'")
    where = f"MuJoCo puts it at {np.round(com, 9).tolist()} m from {whose}"
    if not fused:
        return f"{where}: move the geoms and sites by its negative, or wrap them in {frame} inside body 'target'"
    bodies = tree_masses(path)
    shares = "; ".join(f"{n or 'unnamed'!r} {m:.4g} kg at {_vec(c)}" + ("" if own else " from its geoms")
                       for n, m, c, own in bodies if m > 0)
    hint = f"{where} ({shares})" if bodies else where
    if bodies and bodies[0][3]:  # the target's <inertial> states a mass of its own: the children add theirs
        return (f"{hint}: where the <inertial> of body 'target' holds the whole craft, give the child bodies' geoms "
                "mass='0' (a geom without one weighs its volume times its density, 1000 kg/m^3 by default); else "
                "move its geoms, sites, <inertial> and child bodies by its negative (all but the <inertial> wrapped "
                f"in {frame} inside body 'target')")
    return (f"{hint}: move body 'target''s own geoms and sites and its child bodies by its negative, or wrap them in "
            f"{frame} inside body 'target'")
