"""Off-screen MuJoCo rendering of the chaser camera: grayscale image, depth and segmentation of one view.

The render world is the chaser frame C (the camera mount): the chaser mocap body sits at the origin with the
identity attitude, the target at rho_C with attitude R_C_from_T. Only relative geometry matters to a camera,
so this is the same picture as the truth simulator's inertial world, and the label's x is used as it is.

Two GL passes per view: a lit pass (sun, shadows) read back as RGB, and a flat segmentation pass whose ids
and depth buffer are read back over the target's projected bounding box only. One `SceneRenderer` per worker
process (a GL context costs 0.1-0.3 s). The sun's shadow map covers the target alone: SHADOW_MAP_PX texels across
SHADOW_BOX_REACHES x its reach about its origin (set_view centres the light there), not MuJoCo's +-extent (ENVISAT:
2.3 cm texels, not 4096 of 2.8 cm).
"""

from __future__ import annotations

# MuJoCo picks its GL platform at import: gl_platform chooses a headless one before mujoco loads.
from envisat_pose.datagen.gl_platform import gl_context_class

# isort: split

import cv2
import mujoco
import numpy as np

from envisat_pose.attitude import rotmat_to_quat
from envisat_pose.datagen.appearance import (
    CLASSES,
    GEOM_CLASS,
    OWN_CLASS,
    Appearance,
    class_texture,
    takes_class_appearance,
)
from envisat_pose.datagen.clearance import target_boxes
from envisat_pose.datagen.earth import (
    EARTH_MESH_STEPS_DEG,
    EARTH_SCALE,
    EARTH_TEXTURE_SET_SIZE,
    cap_visible,
    disc_on_rays,
    earth_cap_texture,
    earth_texture,
    mesh_step_for,
    pixel_rays_K,
)
from envisat_pose.datagen.render_model import EARTH_GEOM_GROUP, appearance_classes, render_model_xml
from envisat_pose.datagen.render_pixels import (
    crop_frustum,
    depth_from_buffer,
    intrinsics,
    projected_bbox_px,
    window_box_px,
)
from envisat_pose.datagen.render_view import RenderOutput, RenderPasses, View, target_mask_values
from envisat_pose.datagen.target_scene import scene_xml
from envisat_pose.geometry import CAMERA_NAME
from envisat_pose.target import DEFAULT_TARGET, load_target

# The clutter (ASAR antenna, instrument boxes): geom group 4 of models/envisat.xml, drawn when a view asks.
APPENDAGE_GEOM_GROUP = 4
# The camera frame K of the labels (x right, y down, z boresight) from MuJoCo's camera frame (x right, y up,
# looking along -z).
R_K_FROM_MJCAM = np.diag([1.0, -1.0, -1.0])
SHADOW_MAP_PX, SHADOW_BOX_REACHES = 2048, 1.05


class SceneRenderer:
    """One GL context and MuJoCo scene rendering the chaser camera at a fixed square resolution."""

    @property
    def takes_class_appearance(self) -> bool:
        """The target takes the covering classes' appearance (appearance.takes_class_appearance)."""
        return takes_class_appearance(g.name for g in self.target.geoms)

    def __init__(self, resolution_px: int, shadows: bool = True, base_xml: str | None = None,
                 texture_set_size: int = 0, texture_seed: int = 0, earth_seed: int = 0,
                 earth_texture_set_size: int = EARTH_TEXTURE_SET_SIZE, target: str = DEFAULT_TARGET):
        self.target = load_target(target)
        if base_xml is None:
            base_xml = scene_xml(self.target)
        self.resolution_px = int(resolution_px)
        self.shadows = bool(shadows)
        self.texture_set_size, self.texture_seed = int(texture_set_size), int(texture_seed)
        self.earth_seed, self.earth_texture_set_size = int(earth_seed), int(earth_texture_set_size)
        self.model = mujoco.MjModel.from_xml_string(render_model_xml(self.resolution_px, base_xml,
                                                                     self.texture_set_size,
                                                                     self.earth_texture_set_size))
        self.data = mujoco.MjData(self.model)
        m = self.model
        self.cam_id = m.camera(CAMERA_NAME).id
        self.fovy_deg = float(m.cam_fovy[self.cam_id])
        self.K = intrinsics(self.resolution_px, self.fovy_deg)
        self.qpos_adr = int(m.joint("target_free").qposadr[0])
        self.chaser_mocap = int(m.body("chaser").mocapid[0])
        self.earth_mocap = int(m.body("earth_backdrop").mocapid[0])
        self.earth_geom = m.geom("earth_backdrop").id
        self._earth_mesh = {step: m.mesh(f"earth_sphere_{step:g}").id for step in EARTH_MESH_STEPS_DEG}
        self._earth_matid = {(kind, k): m.material(f"{kind}_{k}").id for kind in ("earth", "earth_cap")
                             for k in range(self.earth_texture_set_size)}
        self._earth_cap_mesh = m.mesh("earth_cap").id
        # the geom's offset changes with its mesh (set_view): MuJoCo must not take it to be the body's frame
        m.geom_sameframe[self.earth_geom] = mujoco.mjtSameFrame.mjSAMEFRAME_NONE.value
        self._earth_uploaded: set[int] = set()  # Earth textures are made and sent at first use
        self._earth_prefetch: dict[tuple[str, int], object] = {}  # (kind, k): Future of its pixels
        self.target_body = m.body("target").id
        self.sun_id = m.light("sun").id
        self.earthshine_id = m.light("earthshine").id
        self._sun_diffuse = m.light_diffuse[self.sun_id].copy()
        self._sun_specular = m.light_specular[self.sun_id].copy()
        # each target geom's MJCF material and, per texture k, its appearance material
        self.mask_values = target_mask_values(self.target)
        if self.takes_class_appearance:
            varied_geoms, classes_of = tuple(GEOM_CLASS), appearance_classes
        else:
            varied_geoms, classes_of = tuple(self.mask_values), lambda name: (OWN_CLASS,)
        self._geom_ids = {name: m.geom(name).id for name in varied_geoms}
        self._mjcf_matid = {name: int(m.geom_matid[g]) for name, g in self._geom_ids.items()}
        self._mjcf_mat = {int(i): (m.mat_rgba[i].copy(), float(m.mat_specular[i]), float(m.mat_shininess[i]),
                                   float(m.mat_reflectance[i])) for i in set(self._mjcf_matid.values())}
        self._appearance_matid = {(name, c, k): m.material(f"appearance_{name}_{c}_{k}").id
                                  for name in varied_geoms for c in classes_of(name)
                                  for k in range(min(self.texture_set_size, 1) if c == OWN_CLASS
                                                 else self.texture_set_size)}
        self.corner_sites = np.array([m.site(s).id for s in self.target.keypoint_sites])  # the K keypoints
        self.target_geoms = np.array([g for g in range(m.ngeom) if m.geom_bodyid[g] == self.target_body])
        self._target_geom_set = {int(g) for g in self.target_geoms}
        self.target_boxes = target_boxes(m)  # the whole target as oriented boxes in T (keep-out, near plane)
        self.mask_lut = np.zeros(m.ngeom + 1, dtype=np.uint8)  # index geom id + 1; -1 (none) -> 0
        for name, value in self.mask_values.items():
            self.mask_lut[m.geom(name).id + 1] = value
        self.znear_m = float(m.vis.map.znear * m.stat.extent)
        self.zfar_m = float(m.vis.map.zfar * m.stat.extent)
        m.vis.map.shadowclip, m.vis.quality.shadowsize = SHADOW_BOX_REACHES * self.target.reach_m / m.stat.extent, SHADOW_MAP_PX
        self._open_gl()
        mujoco.mj_forward(m, self.data)  # the camera's mount: fixed on the chaser at the origin of C
        self._R_K_from_C = self.camera_pose()[0]
        self._frame_rays_K = pixel_rays_K(self.resolution_px, self.K, 8).reshape(-1, 3)  # where the image is, for earth_drawn
        self._upload_textures()

    def _open_gl(self) -> None:
        """The GL context, its two render contexts, the scene, the fixed camera and the read-back buffer."""
        m = self.model
        n = self.resolution_px
        self._gl = gl_context_class()(n, n)
        self._gl.make_current()
        # Two render contexts in one GL context: the lit pass keeps the model's multisampling; the segmentation
        # and depth pass gets a single-sample buffer, so ids and depth are those of the pixel centre (from a
        # multisampled buffer a GPU may return the depth of a sub-sample position: cm off on slanted faces).
        samples = m.vis.quality.offsamples
        m.vis.quality.offsamples = 0
        self._con_seg = mujoco.MjrContext(m, mujoco.mjtFontScale.mjFONTSCALE_100.value)
        self._con_seg.readDepthMap = mujoco.mjtDepthMap.mjDEPTH_ZEROFAR
        m.vis.quality.offsamples = samples
        self._con = mujoco.MjrContext(m, mujoco.mjtFontScale.mjFONTSCALE_100.value)
        self._con.readDepthMap = mujoco.mjtDepthMap.mjDEPTH_ZEROFAR
        mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN.value, self._con)
        self._scene = mujoco.MjvScene(m, maxgeom=100)
        self._opt = mujoco.MjvOption()
        self._cam = mujoco.MjvCamera()
        self._cam.type = mujoco.mjtCamera.mjCAMERA_FIXED
        self._cam.fixedcamid = self.cam_id
        self._rect = mujoco.MjrRect(0, 0, n, n)
        self._rgb = np.empty((n, n, 3), dtype=np.uint8)

    def _upload_textures(self) -> None:
        """Write the procedural textures (appearance.class_texture) into tex_data and send them to both GL
        render contexts; done once per renderer."""
        m = self.model
        for cls in sorted(CLASSES) if self.takes_class_appearance else ():  # another target keeps its own textures
            for k in range(self.texture_set_size):
                t = m.texture(f"tex_{cls}_{k}").id
                data = class_texture(self.texture_seed, cls, k)
                a = int(m.tex_adr[t])
                m.tex_data[a : a + data.size] = data.ravel()
                for con in (self._con, self._con_seg):
                    mujoco.mjr_uploadTexture(m, con, t)
        mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN.value, self._con)

    def _upload_earth_texture(self, kind: str, k: int) -> None:
        """Make Earth texture k of `kind` ('earth': earth.earth_texture, 'earth_cap': earth.earth_cap_texture;
        seeded by earth_seed) and send it to both GL contexts."""
        m = self.model
        t = m.texture(f"{kind}_tex_{k}").id
        fut = self._earth_prefetch.pop((kind, k), None)
        if fut is not None:
            data = fut.result()
        else:
            make = earth_texture if kind == "earth" else earth_cap_texture
            data = make(self.earth_seed, int(m.tex_width[t]), k)
        a = int(m.tex_adr[t])
        m.tex_data[a : a + data.size] = data.ravel()
        self._gl.make_current()
        for con in (self._con, self._con_seg):
            mujoco.mjr_uploadTexture(m, con, t)
        mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN.value, self._con)
        self._earth_uploaded.add((kind, k))

    def prefetch_earth_textures(self) -> None:
        """Start making every Earth texture not yet sent (their pixels: numpy and scipy, no GL) on a helper
        thread, in the order (k, globe then cap); the upload at first use (GL, this thread) then takes the made
        pixels. The pixels are those of the functions called at first use: no byte changes. Hides most of a
        worker's start-up behind its first renders when the machine has a core to spare; for long runs (it
        makes textures a short run may never show). A daemon thread: an exit does not wait for it."""
        import threading
        from concurrent.futures import Future

        todo = [(kind, k) for k in range(self.earth_texture_set_size) for kind in ("earth", "earth_cap")
                if (kind, k) not in self._earth_uploaded and (kind, k) not in self._earth_prefetch]
        if not todo:
            return
        m = self.model
        jobs = []
        for kind, k in todo:
            make = earth_texture if kind == "earth" else earth_cap_texture
            width = int(m.tex_width[m.texture(f"{kind}_tex_{k}").id])
            self._earth_prefetch[(kind, k)] = fut = Future()
            jobs.append((fut, make, width, k))

        def run() -> None:
            for fut, make, width, k in jobs:
                try:
                    fut.set_result(make(self.earth_seed, width, k))
                except BaseException as err:  # surfaces at the upload
                    fut.set_exception(err)

        threading.Thread(target=run, name="earth-texture", daemon=True).start()

    def set_appearance(self, appearance: Appearance | None) -> None:
        """Materials and light intensities of `appearance` into the model arrays (None: the MJCF's own)."""
        m = self.model
        for i, (rgba, spec, shin, refl) in self._mjcf_mat.items():  # an appearance may have written these
            m.mat_rgba[i], m.mat_specular[i], m.mat_shininess[i], m.mat_reflectance[i] = rgba, spec, shin, refl
        for name, g in self._geom_ids.items():
            m.geom_matid[g] = self._mjcf_matid[name]
        if appearance is None:
            m.light_diffuse[self.sun_id], m.light_specular[self.sun_id] = self._sun_diffuse, self._sun_specular
            m.light_active[self.earthshine_id] = 0
            return
        for name, ml in appearance.materials.items():
            if (name, ml.cls, ml.texture) not in self._appearance_matid:
                raise ValueError(f"appearance for geom {name!r} class {ml.cls!r} texture {ml.texture}: this renderer "
                                 f"has {self.texture_set_size} textures per class and no such appearance material")
            i = self._appearance_matid[(name, ml.cls, ml.texture)]
            m.geom_matid[self._geom_ids[name]] = i
            m.mat_rgba[i] = (*ml.rgb, m.mat_rgba[i][3])  # the material's alpha kept: an invisible geom stays so
            m.mat_specular[i], m.mat_shininess[i], m.mat_reflectance[i] = ml.specular, ml.shininess, ml.reflectance
        s = appearance.sun_intensity
        m.light_diffuse[self.sun_id] = (s, s, s)
        m.light_specular[self.sun_id] = (0.5 * s, 0.5 * s, 0.5 * s)
        e = appearance.earthshine_intensity
        m.light_diffuse[self.earthshine_id] = (e, e, e)

    def close(self) -> None:
        """Free the GL resources (also done at interpreter exit by the owner)."""
        if self._con is not None:
            self._gl.make_current()
            self._con.free()
            self._con_seg.free()
            self._con = self._con_seg = None
            self._gl.free()

    def set_view(self, view: View) -> None:
        """Place the target, the sun and the Earth of `view` in the render world (= chaser frame C)."""
        m, d = self.model, self.data
        a = self.qpos_adr
        d.qpos[a : a + 3] = view.rho_C_m
        d.qpos[a + 3 : a + 7] = rotmat_to_quat(np.asarray(view.R_C_from_T))
        d.mocap_pos[self.chaser_mocap] = 0.0
        d.mocap_quat[self.chaser_mocap] = (1.0, 0.0, 0.0, 0.0)
        if view.sun_dir_C is None:
            m.light_active[self.sun_id] = 0
        else:
            s = np.asarray(view.sun_dir_C, dtype=float)
            s = s / np.linalg.norm(s)
            m.light_active[self.sun_id] = 1
            m.light_dir[self.sun_id] = -s  # light travels away from the sun
            # centre the directional light's shadow box on the target
            m.light_pos[self.sun_id] = np.asarray(view.rho_C_m) + s * m.stat.extent
        self.set_appearance(view.appearance)
        self._opt.geomgroup[APPENDAGE_GEOM_GROUP] = int(bool(view.appendages))
        if view.appearance is not None and view.appearance.earthshine_intensity > 0 and view.earth_dir_C is not None:
            e = np.asarray(view.earth_dir_C, dtype=float)
            m.light_active[self.earthshine_id] = 1
            m.light_dir[self.earthshine_id] = -e / np.linalg.norm(e)  # from the Earth toward the target
        else:
            m.light_active[self.earthshine_id] = 0
        if not self.earth_drawn(view):
            self._opt.geomgroup[EARTH_GEOM_GROUP] = 0
            d.mocap_pos[self.earth_mocap] = (0.0, 0.0, -1e5)
        else:
            e = np.asarray(view.earth_dir_C, dtype=float)
            self._opt.geomgroup[EARTH_GEOM_GROUP] = 1
            # shrunk about the camera (the origin of C): the same angular radius asin(R / r), inside the far plane
            d.mocap_pos[self.earth_mocap] = e / np.linalg.norm(e) * view.earth_distance_m * EARTH_SCALE
            q = (1.0, 0.0, 0.0, 0.0) if view.earth_quat_C is None else np.asarray(view.earth_quat_C, dtype=float)
            d.mocap_quat[self.earth_mocap] = np.asarray(q) / np.linalg.norm(q)
            # the detailed cap when all the chaser sees of the Earth lies on it, else the globe at the coarsest
            # level of detail whose limb is within a fraction of a pixel of the circle at this distance
            if cap_visible(view.earth_quat_C, e, view.earth_distance_m):
                kind, m.geom_dataid[self.earth_geom] = "earth_cap", self._earth_cap_mesh
            else:
                kind = "earth"
                m.geom_dataid[self.earth_geom] = self._earth_mesh[mesh_step_for(view.earth_distance_m, self.K[0, 0])]
            # MuJoCo stores a mesh about its centroid and puts the offset in the geom frame: switching meshes
            # takes the new one's offset (the body frame is the Earth's centre)
            mesh = int(m.geom_dataid[self.earth_geom])
            m.geom_pos[self.earth_geom], m.geom_quat[self.earth_geom] = m.mesh_pos[mesh], m.mesh_quat[mesh]
            if self.earth_texture_set_size:
                k = int(view.earth_texture) % self.earth_texture_set_size
                if (kind, k) not in self._earth_uploaded:
                    self._upload_earth_texture(kind, k)
                m.geom_matid[self.earth_geom] = self._earth_matid[(kind, k)]
        mujoco.mj_forward(m, d)

    def earth_drawn(self, view: View) -> bool:
        """Whether `view` draws the Earth: it asks for the backdrop, gives a nadir, and some of the disc (the
        cone of half-angle asin(R / earth_distance_m) about the nadir) falls on the image (pixel rays 8 px
        apart; an Earth out of the frame costs nothing)."""
        if view.earth_dir_C is None or not view.earth_backdrop:
            return False
        return disc_on_rays(self._frame_rays_K, self._R_K_from_C @ np.asarray(view.earth_dir_C, dtype=float),
                            view.earth_distance_m)

    def _earth_out_of_side_passes(self, scn) -> None:
        """The Earth's scene geom casts no shadow (category decor: mjr_render skips it in the shadow map; at
        km it could only shadow itself) and has no segmentation id (the segmentation and depth pass skips it:
        it is background in the mask and the depth). Its 130k triangles are then drawn in the lit pass only."""
        for k in range(scn.ngeom):
            g = scn.geoms[k]
            if g.objtype == mujoco.mjtObj.mjOBJ_GEOM and g.objid == self.earth_geom:
                g.category = mujoco.mjtCatBit.mjCAT_DECOR.value
                g.segid = -1

    def camera_pose(self) -> tuple[np.ndarray, np.ndarray]:
        """(R_K_from_W (3, 3), camera position in W (3,)) from the MJCF camera of the current state."""
        R_W_from_mjcam = self.data.cam_xmat[self.cam_id].reshape(3, 3)
        return R_K_FROM_MJCAM @ R_W_from_mjcam.T, self.data.cam_xpos[self.cam_id].copy()

    def _target_hull_K_m(self, R_K_W: np.ndarray, cam_W: np.ndarray) -> np.ndarray:
        """Corners of every target geom's bounding box in K, (8 G, 3) m: bounds the target's pixels."""
        m, d = self.model, self.data
        signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=float)
        pts = []
        for g in self.target_geoms:
            c, h = m.geom_aabb[g, :3], m.geom_aabb[g, 3:]
            local = c + signs * h
            pts.append(d.geom_xpos[g] + local @ d.geom_xmat[g].reshape(3, 3).T)
        return (np.concatenate(pts) - cam_W) @ R_K_W.T

    def render(self, view: View, labels: bool = True) -> RenderOutput:
        """Render `view`: the lit grayscale image, then depth and segmentation over the target's box (labels False:
        the lit pass alone, depth_m and mask_u8 None; the closed loop). render = decode(render_passes(...))."""
        return self.decode(self.render_passes(view, labels))

    def render_passes(self, view: View, labels: bool = True) -> RenderPasses:
        """The GL part of render: both passes of `view`, read back into fresh arrays (a caller may decode them
        beside the next view's passes)."""
        n = self.resolution_px
        scn = self._lit_scene(view)
        flags = scn.flags
        R_K_W, cam_W = self.camera_pose()
        target_box = projected_bbox_px(self._target_hull_K_m(R_K_W, cam_W), self.K, n, self.znear_m)
        box = target_box if labels else None
        # pass 1: the lit image, full frame (read back over the target's box where nothing else is drawn)
        mujoco.mjr_render(self._rect, scn, self._con)
        rgb = self._read_lit(scn, target_box)
        raw = ids_rgb = slot_value = None
        if box is not None:
            # pass 2: flat segmentation colours (one id per geom) and depth of the target's box only: the
            # frustum is narrowed to the box's pixels and the viewport shrunk to match, so each pixel keeps its
            # full-image ray. Depth and mask come from this one pass so they cover the same pixels.
            flags[mujoco.mjtRndFlag.mjRND_SEGMENT] = True
            flags[mujoco.mjtRndFlag.mjRND_IDCOLOR] = True
            flags[mujoco.mjtRndFlag.mjRND_SHADOW] = False
            crop_rect = self._render_box(scn, box, self._con_seg)
            flags[mujoco.mjtRndFlag.mjRND_SEGMENT] = False
            flags[mujoco.mjtRndFlag.mjRND_IDCOLOR] = False
            raw = np.empty((crop_rect.height, crop_rect.width), dtype=np.float32)
            ids_rgb = np.empty(raw.shape + (3,), dtype=np.uint8)
            mujoco.mjr_readPixels(ids_rgb, raw, crop_rect, self._con_seg)
            mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN.value, self._con)
            # segmentation colour -> scene slot + 1 (0: background) -> geom -> mask value, as one lookup table
            slot_value = np.zeros(max(scn.ngeom + 1, 256), dtype=np.uint8)
            for k in range(scn.ngeom):
                g = scn.geoms[k]
                if g.objtype == mujoco.mjtObj.mjOBJ_GEOM and g.segid >= 0:
                    slot_value[g.segid + 1] = self.mask_lut[g.objid + 1]
        return RenderPasses(rgb, box, ids_rgb, raw, slot_value, *self._pose_K(R_K_W, cam_W))

    def _pose_K(self, R_K_W: np.ndarray, cam_W: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The current state's (corners_K_m (K, 3) m, R_K_from_T (3, 3), t_K_from_T_m (3,) m) in the camera frame."""
        d = self.data
        R_W_T = d.xmat[self.target_body].reshape(3, 3)
        return ((d.site_xpos[self.corner_sites] - cam_W) @ R_K_W.T, R_K_W @ R_W_T,
                R_K_W @ (d.xpos[self.target_body] - cam_W))

    def _lit_scene(self, view: View):
        """Place `view` (set_view) and make its MjvScene ready for the lit pass (the Earth out of the side passes
        and drawn once, shadows as the renderer says); the GL context current."""
        self.set_view(view)
        self._gl.make_current()
        scn = self._scene
        mujoco.mjv_updateScene(self.model, self.data, self._opt, None, self._cam, mujoco.mjtCatBit.mjCAT_ALL.value, scn)
        self._earth_out_of_side_passes(scn)
        scn.flags[mujoco.mjtRndFlag.mjRND_ADDITIVE] = True  # the one transparent geom (the Earth) drawn once
        scn.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = self.shadows
        return scn

    def _render_box(self, scn, box: tuple[int, int, int, int], con) -> mujoco.MjrRect:
        """Draw scn over the pixel box (u0, v0, u1, v1) of the full image only, into con's offscreen buffer: the
        frustum narrowed to the box's pixels (crop_frustum) and the viewport shrunk to the box, so every pixel
        keeps its full-image ray; the frustums are restored after (a following full render is unchanged).
        Returns the viewport (its pixels in GL row order: read them with mjr_readPixels(..., viewport, con))."""
        u0, v0, u1, v1 = box
        saved = [(c.frustum_center, c.frustum_width, c.frustum_bottom, c.frustum_top) for c in scn.camera]
        for c in scn.camera:
            c.frustum_center, c.frustum_width, c.frustum_bottom, c.frustum_top = crop_frustum(
                box, self.resolution_px, c.frustum_bottom, c.frustum_top)
        rect = mujoco.MjrRect(0, 0, u1 - u0 + 1, v1 - v0 + 1)
        mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN.value, con)
        mujoco.mjr_render(rect, scn, con)
        for c, (fc, fw, fb, ft) in zip(scn.camera, saved):
            c.frustum_center, c.frustum_width, c.frustum_bottom, c.frustum_top = fc, fw, fb, ft
        return rect

    def render_window(self, view: View, window_px: tuple[int, int, int]) -> RenderOutput:
        """The lit image of the square window (x0, y0, side) px of the full frame alone (the closed loop's region
        of interest), drawn as pass 2 draws its box (_render_box): gray_u8 (side, side) uint8, row 0 the frame's
        row y0, 0 outside the image; the pose as render gives it. render(view, False).gray_u8[y0:y0 + side, x0:x0 +
        side] up to the rasterizer (osmesa: 0.73 % of the tests' pixels take another multisample, at most 92 levels,
        0.17 mean; test_render_window.py allows twice that). Leaves the frustums as a full render found them."""
        x0, y0, side = window_px
        box = window_box_px(window_px, self.resolution_px)
        scn = self._lit_scene(view)
        gray = np.zeros((side, side), dtype=np.uint8)
        if box is not None:
            u0, v0, u1, v1 = box
            rect = self._render_box(scn, box, self._con)
            rgb = np.empty((rect.height, rect.width, 3), dtype=np.uint8)
            mujoco.mjr_readPixels(rgb, None, rect, self._con)
            # GL rows run bottom-up
            gray[v0 - y0 : v1 + 1 - y0, u0 - x0 : u1 + 1 - x0] = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)[::-1]
        return RenderOutput(gray, None, None, *self._pose_K(*self.camera_pose()), self.fovy_deg)

    def view_pose(self, view: View) -> RenderOutput:
        """`view` placed (set_view) and nothing drawn: the pose of render(view) (gray_u8, depth_m, mask_u8 None)."""
        self.set_view(view)
        return RenderOutput(None, None, None, *self._pose_K(*self.camera_pose()), self.fovy_deg)

    def decode(self, p: RenderPasses) -> RenderOutput:
        """The pixel work of render: gray image, mask and depth of read-back passes (numpy and OpenCV only; no
        GL state, so it may run beside the next render_passes)."""
        n = self.resolution_px
        gray = cv2.flip(cv2.cvtColor(p.rgb_u8, cv2.COLOR_RGB2GRAY), 0)  # GL rows run bottom-up
        depth_m = mask = None
        if p.box is not None:
            u0, v0, u1, v1 = p.box
            depth_m = np.zeros((n, n), dtype=np.float32)
            mask = np.zeros((n, n), dtype=np.uint8)
            ids_rgb = p.ids_rgb_u8
            if len(p.slot_value) <= 256:  # ids fit the red channel
                crop_mask = p.slot_value[ids_rgb[..., 0]]
            else:
                seg = ids_rgb.astype(np.int32)
                crop_mask = p.slot_value[np.clip(seg[..., 0] + (seg[..., 1] << 8) + (seg[..., 2] << 16), 0,
                                                 len(p.slot_value) - 1)]
            crop_mask = crop_mask[::-1]  # GL rows run bottom-up
            fg = crop_mask > 0
            crop_depth = np.zeros(p.depth_raw.shape, dtype=np.float32)
            crop_depth[fg] = depth_from_buffer(p.depth_raw[::-1][fg], self.znear_m, self.zfar_m)
            mask[v0 : v1 + 1, u0 : u1 + 1] = crop_mask
            depth_m[v0 : v1 + 1, u0 : u1 + 1] = crop_depth
        return RenderOutput(gray_u8=gray, depth_m=depth_m, mask_u8=mask, corners_K_m=p.corners_K_m,
                            R_K_from_T=p.R_K_from_T, t_K_from_T_m=p.t_K_from_T_m, fovy_deg=self.fovy_deg)

    def _read_lit(self, scn, target_box: tuple[int, int, int, int] | None) -> np.ndarray:
        """The lit pass read back, (n, n, 3) uint8 in GL row order. When every geom drawn is the target's, only its
        box is read (the rest is the clear colour, left 0; tests/datagen/test_render_labels.py compares with the
        full read); a scene with any other geom (the Earth) is read whole."""
        n = self.resolution_px
        only_target = all(scn.geoms[k].objtype == mujoco.mjtObj.mjOBJ_GEOM
                          and scn.geoms[k].objid in self._target_geom_set for k in range(scn.ngeom))
        if not only_target:
            rgb = np.empty((n, n, 3), dtype=np.uint8)
            mujoco.mjr_readPixels(rgb, None, self._rect, self._con)
            return rgb
        rgb = np.zeros((n, n, 3), dtype=np.uint8)
        if target_box is not None:
            u0, v0, u1, v1 = target_box
            w, h = u1 - u0 + 1, v1 - v0 + 1
            sub = np.empty((h, w, 3), dtype=np.uint8)
            mujoco.mjr_readPixels(sub, None, mujoco.MjrRect(u0, n - 1 - v1, w, h), self._con)  # GL rows bottom-up
            rgb[n - 1 - v1:n - v0, u0:u1 + 1] = sub
        return rgb

    def render_rgb_only(self, view: View) -> np.ndarray:
        """The lit pass alone, read back as RGB (H, W, 3): the raw render the benchmark compares against."""
        mujoco.mjr_render(self._rect, self._lit_scene(view), self._con)
        mujoco.mjr_readPixels(self._rgb, None, self._rect, self._con)
        return self._rgb[::-1]
