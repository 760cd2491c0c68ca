"""Frames the project never trained on: the poses of a project sequence, another renderer, a real camera's
habits on top, written as a user would hand them to `envisat track` / `envisat adapt`.

The poses and the sun are those of `envisat generate --mode sequence --scenario S --seed K --num-images N
--resolution R` (datagen.views.sequence_frames: the same MuJoCo truth). The renderer is MuJoCo's Filament
(physically based) renderer, headless through Vulkan on Mesa's lavapipe (Debian's mesa-vulkan-drivers;
../shared/platform-notes.md): metallic foil with a roughness, photometric sunlight (a directional light in lux), no
ambient, no Earth, tone-mapped by Filament, none of datagen/appearance.py's appearance draws. On top, a camera the space
camera model (datagen/sensor.py) never drew:
- a lens with radial and tangential distortion (OpenCV's k1, k2, p1, p2) and a principal point a few pixels off
  the centre (the calibration goes into camera.toml, as a user would calibrate their camera);
- a small-pixel sensor: Poisson-Gaussian noise with a low full well (FULL_WELL_E electrons at white, where the
  project draws 8000-30000), a read noise, a black-level pedestal the project never adds, 8 bits;
- JPEG compression (quality JPEG_QUALITY: 8x8 block artefacts on the edges).

Output folder (one per scenario, seed and resolution):
    frames/frame_00000.jpg ...   the images (gray JPEG)
    timestamps.csv               file,t_s (pipelines/runs/frame_names.py read_timestamps)
    camera.toml                  fx, fy, cx, cy, width, height, distortion (pipelines/tracking/camera_file.py)
    truth.npz                    for scoring only, never read by the tracker: t_s (N,), x (N, 12), corners_px
                                 (N, 8, 2) in the distorted frames, corners_ideal_px (N, 8, 2) through the ideal
                                 pinhole the tracker remaps to, visible (N, 8) (face test), in_frame (N, 8),
                                 eclipse (N,), config_json
    meta.json                    how it was made (renderer, habits, timing)

Run:  .venv/bin/python bench/foreign_frames.py --scenario default --seed 0 --num-images 240 \\
          --resolution 512 --out /tmp/foreign-default-0-512
Where Filament cannot start (no Vulkan driver), the script says so in one line and exits 2. Nothing in the tests
needs Vulkan: tests/bench/test_foreign_frames.py tests the camera's habits alone and skips the render where
Filament is absent.
"""

from __future__ import annotations

import collections.abc
import json
import os
import sys
import time
import xml.etree.ElementTree as ET
from dataclasses import asdict, dataclass

import numpy as np

LVP_ICD = "/usr/share/vulkan/icd.d/lvp_icd.x86_64.json"
SUN_LUX = 6.0e4  # photometric sunlight, lux, under Filament's default camera exposure (f/16, 1/125 s, ISO 100)
EARTHSHINE_LUX = 1.5e4  # sunlight off the Earth, from the nadir (-x_C), no shadows
FULL_WELL_E = 2500.0
READ_NOISE_E = 4.0
BLACK_LEVEL_DN = 4.0
JPEG_QUALITY = 85
# the foreign lens (OpenCV's model, normalized coordinates): mild barrel distortion and a decentred element
DISTORTION = (-0.12, 0.05, 4e-4, -3e-4)  # k1, k2, p1, p2
PRINCIPAL_OFFSET_FRAC = (3.2 / 1024.0, -2.1 / 1024.0)  # of the image side, (u, v)
# Filament's physically based materials for the MJCF's own: metallic foil, painted panels, cells
PBR_MATERIALS = {"foil": {"metallic": "1", "roughness": "0.55"},
                 "foil_silver": {"metallic": "1", "roughness": "0.45"},
                 "panel": {"metallic": "0", "roughness": "0.75"},
                 "array": {"metallic": "0.3", "roughness": "0.15"},
                 "boom": {"metallic": "1", "roughness": "0.5"}}


# ---------------------------------------------------------------------------------------------------------
# The camera's habits (pure numpy / OpenCV; no renderer)


@dataclass(frozen=True)
class Habits:
    """A real camera's habits. distortion: OpenCV's (k1, k2, p1, p2); principal_offset_frac: the principal
    point's offset from the image centre, share of the side (u, v); full_well_e: electrons at white (255 of the
    render); read_noise_e: e- RMS; black_level_dn: pedestal, DN; jpeg_quality: 1-100 (0: PNG, lossless)."""

    distortion: tuple[float, float, float, float] = DISTORTION
    principal_offset_frac: tuple[float, float] = PRINCIPAL_OFFSET_FRAC
    full_well_e: float = FULL_WELL_E
    read_noise_e: float = READ_NOISE_E
    black_level_dn: float = BLACK_LEVEL_DN
    jpeg_quality: int = JPEG_QUALITY


def ideal_K(size_px: int, f_px: float) -> np.ndarray:
    """The renderer's pinhole (3, 3): f px, principal point at the image centre ((N - 1) / 2)."""
    c = 0.5 * (size_px - 1)
    return np.array([[f_px, 0.0, c], [0.0, f_px, c], [0.0, 0.0, 1.0]])


def foreign_K(size_px: int, f_px: float, habits: Habits) -> np.ndarray:
    """The foreign camera's intrinsics (3, 3): the same focal length, the principal point off the centre."""
    K = ideal_K(size_px, f_px)
    K[0, 2] += habits.principal_offset_frac[0] * size_px
    K[1, 2] += habits.principal_offset_frac[1] * size_px
    return K


def distort_px(points_ideal_px: np.ndarray, K_ideal: np.ndarray, K_cam: np.ndarray,
               distortion: tuple[float, ...]) -> np.ndarray:
    """Where the foreign camera images points that the ideal pinhole puts at points_ideal_px (..., 2) px:
    normalized x = K_ideal^-1 p, then OpenCV's model (r^2 = x^2 + y^2)
        x_d = x (1 + k1 r^2 + k2 r^4) + 2 p1 x y + p2 (r^2 + 2 x^2)
        y_d = y (1 + k1 r^2 + k2 r^4) + p1 (r^2 + 2 y^2) + 2 p2 x y
    and p_d = K_cam x_d. (..., 2) px."""
    k1, k2, p1, p2 = distortion
    p = np.asarray(points_ideal_px, dtype=float)
    x = (p[..., 0] - K_ideal[0, 2]) / K_ideal[0, 0]
    y = (p[..., 1] - K_ideal[1, 2]) / K_ideal[1, 1]
    r2 = x * x + y * y
    radial = 1.0 + k1 * r2 + k2 * r2 * r2
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return np.stack([K_cam[0, 0] * xd + K_cam[0, 2], K_cam[1, 1] * yd + K_cam[1, 2]], axis=-1)


def undistort_px(points_cam_px: np.ndarray, K_ideal: np.ndarray, K_cam: np.ndarray,
                 distortion: tuple[float, ...], iterations: int = 30) -> np.ndarray:
    """The inverse of distort_px: the ideal pinhole's pixels (..., 2) of the foreign camera's pixels (..., 2), by
    the fixed-point iteration x = (x_d - tangential(x)) / radial(x) (converges for a lens this mild; the residual
    is checked: a RuntimeError above 1e-6 px)."""
    k1, k2, p1, p2 = distortion
    q = np.asarray(points_cam_px, dtype=float)
    xd = (q[..., 0] - K_cam[0, 2]) / K_cam[0, 0]
    yd = (q[..., 1] - K_cam[1, 2]) / K_cam[1, 1]
    x, y = xd.copy(), yd.copy()
    for _ in range(iterations):
        r2 = x * x + y * y
        radial = 1.0 + k1 * r2 + k2 * r2 * r2
        x = (xd - 2.0 * p1 * x * y - p2 * (r2 + 2.0 * x * x)) / radial
        y = (yd - p1 * (r2 + 2.0 * y * y) - 2.0 * p2 * x * y) / radial
    out = np.stack([K_ideal[0, 0] * x + K_ideal[0, 2], K_ideal[1, 1] * y + K_ideal[1, 2]], axis=-1)
    err = np.abs(distort_px(out, K_ideal, K_cam, distortion) - q).max(initial=0.0)
    if err > 1e-6:
        raise RuntimeError(f"the lens does not invert: residual {err:.2g} px")
    return out


def distortion_maps(size_px: int, K_ideal: np.ndarray, K_cam: np.ndarray, distortion: tuple[float, ...]
                    ) -> tuple[np.ndarray, np.ndarray]:
    """cv2.remap maps (map_x, map_y) (H, W) float32 that make the foreign camera's image of an ideal render: for
    each pixel of the distorted image, where the ideal render saw the same ray (undistort_px)."""
    v, u = np.mgrid[0:size_px, 0:size_px].astype(np.float64)
    und = undistort_px(np.stack([u, v], axis=-1), K_ideal, K_cam, distortion).astype(np.float32)
    return und[..., 0], und[..., 1]


def camera_habits(ideal_u8: np.ndarray, maps: tuple[np.ndarray, np.ndarray], habits: Habits,
                  rng: np.random.Generator) -> np.ndarray:
    """The foreign camera's 8-bit frame of an ideal render (H, W) uint8: the lens (remap through maps, bilinear),
    then the sensor: electrons = value / 255 x full well, Poisson shot noise, Gaussian read noise, the pedestal,
    rounded and clipped to 8 bits. JPEG is applied when written (encode_frame). Returns (H, W) uint8."""
    import cv2

    lens = cv2.remap(ideal_u8.astype(np.float32), maps[0], maps[1], cv2.INTER_LINEAR, borderValue=0.0)
    gain_e_per_dn = habits.full_well_e / 255.0
    electrons = rng.poisson(np.maximum(lens, 0.0) * gain_e_per_dn).astype(np.float64)
    electrons += rng.normal(0.0, habits.read_noise_e, size=electrons.shape)
    dn = electrons / gain_e_per_dn + habits.black_level_dn
    return np.clip(np.rint(dn), 0, 255).astype(np.uint8)


def encode_frame(frame_u8: np.ndarray, jpeg_quality: int) -> tuple[bytes, str]:
    """The frame's file bytes and extension: JPEG at jpeg_quality (1-100), PNG at 0."""
    import cv2

    if jpeg_quality > 0:
        ok, buf = cv2.imencode(".jpg", frame_u8, [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)])
        ext = ".jpg"
    else:
        ok, buf = cv2.imencode(".png", frame_u8)
        ext = ".png"
    if not ok:
        raise RuntimeError("OpenCV could not encode a frame")
    return buf.tobytes(), ext


def camera_toml_text(K_cam: np.ndarray, size_px: int, distortion: tuple[float, ...]) -> str:
    """The foreign camera's calibration as the camera file `envisat track --camera` reads (pipelines/tracking/camera_file.py:
    fx, fy, cx, cy px, width, height, OpenCV distortion k1, k2, p1, p2)."""
    d = ", ".join(repr(float(v)) for v in distortion)
    return ("# the foreign camera's calibration (OpenCV model), as a user would give it to envisat track\n"
            f"fx = {float(K_cam[0, 0])!r}\nfy = {float(K_cam[1, 1])!r}\ncx = {float(K_cam[0, 2])!r}\n"
            f"cy = {float(K_cam[1, 2])!r}\nwidth = {int(size_px)}\nheight = {int(size_px)}\ndistortion = [{d}]\n")


# ---------------------------------------------------------------------------------------------------------
# The Filament renderer


def _buffer_stand_in() -> None:
    """mujoco.rendering.filament imports collections.abc.Buffer (Python 3.12, PEP 688): on 3.11 a stand-in that
    takes anything memoryview takes (platform notes)."""
    if hasattr(collections.abc, "Buffer"):
        return

    class _BufferMeta(type):
        def __instancecheck__(cls, obj) -> bool:
            try:
                memoryview(obj)
            except TypeError:
                return False
            return True

    class Buffer(metaclass=_BufferMeta):
        pass

    collections.abc.Buffer = Buffer


def filament_problem() -> str | None:
    """Why Filament cannot render here (one line), or None when it can (its modules import and a Vulkan ICD of
    Mesa's lavapipe is installed). Starting a context is left to FilamentRenderer."""
    if not os.path.exists(LVP_ICD) and not os.environ.get("VK_ICD_FILENAMES"):
        return f"no Vulkan driver: {LVP_ICD} is missing (apt-get install mesa-vulkan-drivers)"
    try:
        _buffer_stand_in()
        import mujoco.studio.window  # noqa: F401  (registers Filament's resource providers first)
        from mujoco import mjrf  # noqa: F401
        from mujoco.rendering.filament.renderer import Renderer  # noqa: F401
    except ImportError as err:
        return f"MuJoCo's Filament renderer does not import: {err}"
    return None


def foreign_model_xml(resolution_px: int, sun_lux: float = SUN_LUX, earthshine_lux: float = EARTHSHINE_LUX) -> str:
    """models/envisat.xml for Filament: physically based materials (PBR_MATERIALS: metallic, roughness), the sun a
    photometric directional light (intensity in lux), Earth-shine a second one from the nadir (-x_C: the hold is
    on V-bar), no headlight, the off-screen buffer at the resolution. The XML tree is edited in memory."""
    from envisat_pose.geometry import model_path

    root = ET.parse(model_path()).getroot()
    for mat in root.iter("material"):
        for k, v in PBR_MATERIALS.get(mat.get("name"), {}).items():
            mat.set(k, v)
    for light in root.iter("light"):
        if light.get("name") == "sun":
            light.set("intensity", repr(float(sun_lux)))
    ET.SubElement(root.find("worldbody"), "light", name="earthshine", directional="true", castshadow="false",
                  pos="-100 0 0", dir="1 0 0", intensity=repr(float(earthshine_lux)))
    visual = root.find("visual")
    glob = visual.find("global") if visual.find("global") is not None else ET.SubElement(visual, "global")
    glob.set("offwidth", str(max(resolution_px, 1024)))
    glob.set("offheight", str(max(resolution_px, 1024)))
    head = visual.find("headlight")
    if head is not None:
        head.set("ambient", "0 0 0")
    return ET.tostring(root, encoding="unicode")


class FilamentRenderer:
    """One Filament context (Vulkan, lavapipe) rendering the chaser camera of the foreign model at a square size.
    render(rho_C_m, R_C_from_T, sun_dir_C) -> (H, W) uint8 gray. One read request per render call."""

    def __init__(self, resolution_px: int, sun_lux: float = SUN_LUX):
        from envisat_pose.config import InputError

        problem = filament_problem()
        if problem:  # a user's machine to set up: one line under bench/_common.run_main (adapt, edge_truth)
            raise InputError(problem)
        if os.path.exists(LVP_ICD):
            os.environ.setdefault("VK_ICD_FILENAMES", LVP_ICD)
        import mujoco
        from mujoco import mjrf
        from mujoco.rendering.filament.model_scene import ModelScene
        from mujoco.rendering.filament.renderer import Renderer

        self._mujoco = mujoco
        self.n = int(resolution_px)
        self.model = mujoco.MjModel.from_xml_string(foreign_model_xml(self.n, sun_lux))
        self.data = mujoco.MjData(self.model)
        m = self.model
        self.qpos_adr = int(m.joint("target_free").qposadr[0])
        self.sun_id = m.light("sun").id
        self.sun_intensity = float(m.light_intensity[self.sun_id])
        self.cam_id = m.camera("chaser_cam").id
        fovy = float(m.cam_fovy[self.cam_id])
        self.f_px = 0.5 * self.n / np.tan(np.radians(fovy) / 2.0)
        ctx = mjrf.Context(mjrf.ContextConfig(graphics_api=mjrf.GraphicsApi.GRAPHICS_API_VULKAN))
        self._renderer = Renderer(ctx)
        self._scene = ModelScene(ctx, m, self._renderer.scene("scn"))
        self._rgb = np.zeros((self.n, self.n, 3), dtype=np.uint8)
        self._renderer.target("out", self._rgb)
        self._mjv_scene = mujoco.MjvScene(m, maxgeom=100)
        self._opt = mujoco.MjvOption()
        self._cam = mujoco.MjvCamera()
        self._cam.type = mujoco.mjtCamera.mjCAMERA_FIXED
        self._cam.fixedcamid = self.cam_id

    def render(self, rho_C_m: np.ndarray, R_C_from_T: np.ndarray, sun_dir_C: np.ndarray | None) -> np.ndarray:
        """The gray frame (H, W) uint8 of the target at rho_C_m (3,) m with attitude R_C_from_T (3, 3), lit from
        sun_dir_C (3,) (toward the sun, in C; None: eclipse, a black frame but for nothing)."""
        import cv2

        mujoco, m, d = self._mujoco, self.model, self.data
        from mujoco.rendering.filament.renderer import View

        from envisat_pose.attitude import rotmat_to_quat

        a = self.qpos_adr
        d.qpos[a:a + 3] = rho_C_m
        d.qpos[a + 3:a + 7] = rotmat_to_quat(np.asarray(R_C_from_T, dtype=float))
        if sun_dir_C is None:
            m.light_active[self.sun_id] = 0
        else:
            s = np.asarray(sun_dir_C, dtype=float)
            m.light_active[self.sun_id] = 1
            m.light_dir[self.sun_id] = -s / np.linalg.norm(s)
            m.light_pos[self.sun_id] = np.asarray(rho_C_m) + s / np.linalg.norm(s) * m.stat.extent
        mujoco.mj_forward(m, d)
        mujoco.mjv_updateScene(m, d, self._opt, None, self._cam, mujoco.mjtCatBit.mjCAT_ALL.value, self._mjv_scene)
        self._scene.update(d)
        self._renderer.render([View(scene="scn", target="out", camera=self.gl_camera(), skybox=False, haze=False,
                                    headlight=False)])
        return cv2.cvtColor(self._rgb, cv2.COLOR_RGB2GRAY)

    def gl_camera(self):
        """The chaser camera of the last updated scene, as MuJoCo's own renderer draws it: the average of the
        scene's two eyes (mjv_averageCamera). mjv_updateScene puts camera[0] and camera[1] ipd / 2 (the model's
        visual/global ipd, 0.068 m) to the left and right of the camera; mjr_render averages them for a mono
        view. Rendering from camera[0] put the camera 3.4 cm to the left of the truth's: the target +0.64 px to
        the right at 50 m and 512 px (bench/foreign_scale.py)."""
        return self._mujoco.mjv_averageCamera(self._mjv_scene.camera[0], self._mjv_scene.camera[1])

    def segmentation(self) -> np.ndarray:
        """The mask (H, W) uint8 of the last rendered view in the project's values (datagen/render_view.MASK_VALUES:
        box faces 1-6, array and boom 7, background 0), from Filament's segmentation pass (red = geom id + 1)."""
        from mujoco import mjrf
        from mujoco.rendering.filament.renderer import View

        from envisat_pose.datagen.render_view import MASK_VALUES

        self._renderer.render([View(scene="scn", target="out", camera=self.gl_camera(), skybox=False, haze=False,
                                    headlight=False, post_processing=False,
                                    draw_mode=mjrf.DrawMode.DRAW_MODE_SEGMENTATION_BY_ID)])
        m = self.model
        lut = np.zeros(256, dtype=np.uint8)
        for g in range(min(m.ngeom, 255)):
            lut[g + 1] = MASK_VALUES.get(m.geom(g).name, 0)
        return lut[self._rgb[..., 0]]


# ---------------------------------------------------------------------------------------------------------
# A sequence


def sequence_truth(scenario: str, seed: int, num_images: int, resolution_px: int, frame_dt_s: float = 1.0,
                   lit_sun: bool = True):
    """The poses and sun of `envisat generate --mode sequence` for (scenario, seed, num_images, resolution,
    frame_dt_s, sun_dir): (t_s (N,), x (N, 12), sun_dir_C (N, 3), eclipse (N,) bool, config_json). lit_sun: the
    sun is the seed's lit sun of the closed-loop benchmarks (pipelines/runs/trials.scenario_sun_N: the camera sees a
    sunlit side on every frame), given to generate as its sun_dir; else generate's own draw from the seed."""
    from envisat_pose.datagen.generate_config import GenerateConfig, SequenceModeConfig, config_json
    from envisat_pose.datagen.views import sequence_frames
    from envisat_pose.pipelines.runs.trials import scenario_sun_N

    sun_N = scenario_sun_N(scenario, (num_images - 1) * frame_dt_s, 1.0 / frame_dt_s, seed) if lit_sun else None
    cfg = GenerateConfig(mode="sequence", num_images=num_images, resolution_px=resolution_px, seed=seed,
                         sequence=SequenceModeConfig(scenario, frame_dt_s), sun_dir=sun_N)
    text = config_json(cfg)
    t_s, x, sun_C, eclipse, _ = sequence_frames(text)
    return t_s, x, sun_C, eclipse, text


def make_sequence(out_dir: str, scenario: str, seed: int, num_images: int, resolution_px: int,
                  frame_dt_s: float = 1.0, habits: Habits = Habits(), progress: bool = True,
                  made_by: dict | None = None) -> dict:
    """Render and write one foreign sequence into out_dir (module docstring). Returns meta.json's content, which
    records made_by (the command's provenance) under "provenance" when given."""
    from envisat_pose.attitude import mrp_to_dcm
    from envisat_pose.geometry import PinholeCamera, load_camera
    from envisat_pose.io import atomic_path, atomic_write_text, save_npz
    from envisat_pose.pipelines.adaptation.pseudo_labels import corner_labels
    from envisat_pose.state import MRP, POS

    t_s, x, sun_C, eclipse, cfg_json = sequence_truth(scenario, seed, num_images, resolution_px, frame_dt_s)
    n = int(resolution_px)
    renderer = FilamentRenderer(n)
    K_i = ideal_K(n, renderer.f_px)
    K_c = foreign_K(n, renderer.f_px, habits)
    maps = distortion_maps(n, K_i, K_c, habits.distortion)
    os.makedirs(os.path.join(out_dir, "frames"), exist_ok=True)
    rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(0xF0E1,)))
    names, render_s, habit_s = [], 0.0, 0.0
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(t_s), unit="frame", desc=f"filament {scenario} seed {seed} {n} px")
    for k in range(len(t_s)):
        t0 = time.perf_counter()
        ideal = renderer.render(x[k, POS], mrp_to_dcm(x[k, MRP]).T, None if eclipse[k] else sun_C[k])
        t1 = time.perf_counter()
        frame = camera_habits(ideal, maps, habits, rng)
        data, ext = encode_frame(frame, habits.jpeg_quality)
        t2 = time.perf_counter()
        render_s, habit_s = render_s + t1 - t0, habit_s + t2 - t1
        name = f"frame_{k:05d}{ext}"
        with atomic_path(os.path.join(out_dir, "frames", name)) as tmp:
            with open(tmp, "wb") as fh:
                fh.write(data)
        names.append(name)
        if bar is not None:
            bar.update(1)
    if bar is not None:
        bar.close()
    atomic_write_text(os.path.join(out_dir, "timestamps.csv"),
                      "file,t_s\n" + "".join(f"{nm},{t!r}\n" for nm, t in zip(names, t_s.tolist())))
    atomic_write_text(os.path.join(out_dir, "camera.toml"), camera_toml_text(K_c, n, habits.distortion))
    ideal_cam = load_camera().scaled(n, n)
    lab = corner_labels(x, ideal_cam)
    # the pinhole the tracker remaps the frames to: f = sqrt(fx fy), principal point (cx, cy) (camera_file.py)
    remapped = PinholeCamera(float(K_c[0, 0]), float(K_c[0, 2]), float(K_c[1, 2]), n, n,
                             ideal_cam.R_K_from_C, ideal_cam.pos_C_m)
    save_npz(os.path.join(out_dir, "truth.npz"), {
        "t_s": t_s, "x": x, "corners_px": distort_px(lab["corners_px"], K_i, K_c, habits.distortion),
        "corners_ideal_px": corner_labels(x, remapped)["corners_px"], "visible": lab["visible"],
        "in_frame": lab["in_frame"], "eclipse": eclipse, "config_json": np.array(cfg_json)})
    sun_N = json.loads(cfg_json)["sun_dir"]
    meta = {"scenario": scenario, "seed": seed, "sun_dir_N": sun_N, "num_images": len(t_s), "resolution_px": n,
            "frame_dt_s": frame_dt_s, "renderer": "MuJoCo Filament (Vulkan, Mesa lavapipe), PBR materials "
            f"{PBR_MATERIALS}, sun {renderer.sun_intensity:g} lux, no ambient, no Earth",
            "habits": asdict(habits), "render_s_per_frame": render_s / len(t_s),
            "habits_s_per_frame": habit_s / len(t_s), "same_poses_as": f"envisat generate --mode sequence "
            f"--scenario {scenario} --seed {seed} --num-images {num_images} --resolution {n}, sun_dir = {sun_N} in "
            "its --config"} | ({} if made_by is None else {"provenance": made_by})
    atomic_write_text(os.path.join(out_dir, "meta.json"), json.dumps(meta, indent=1, sort_keys=True) + "\n")
    return meta


def main(argv: list[str] | None = None) -> int:
    from _common import WholeFlagParser, count, description, positive, provenance  # bench/_common.py

    ap = WholeFlagParser(description=description(__doc__))
    ap.add_argument("--scenario", default="default")
    ap.add_argument("--seed", type=count(0), default=0)
    ap.add_argument("--num-images", type=count(), default=240)
    ap.add_argument("--resolution", type=count(), default=512)
    ap.add_argument("--frame-dt-s", type=positive, default=1.0)
    ap.add_argument("--jpeg-quality", type=int, default=JPEG_QUALITY)
    ap.add_argument("--out", required=True)
    a = ap.parse_args(argv)
    problem = filament_problem()
    if problem:
        print(f"foreign_frames: {problem}", file=sys.stderr)
        return 2
    meta = make_sequence(a.out, a.scenario, a.seed, a.num_images, a.resolution, a.frame_dt_s,
                         Habits(jpeg_quality=a.jpeg_quality), made_by=provenance(a))
    print(f"{meta['num_images']} frames in {a.out}: render {1000 * meta['render_s_per_frame']:.0f} ms/frame, "
          f"habits {1000 * meta['habits_s_per_frame']:.0f} ms/frame")
    return 0


if __name__ == "__main__":
    from _common import run_main  # bench/_common.py, beside this script

    run_main(main)
