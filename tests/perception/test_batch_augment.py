"""The batched device augmentation (perception/batch_augment.py) against the numpy path of perception/data.py:
the crop rule, the resize, the targets (equal), the style and line statistics, and a crop's labels against a
render with the equivalent camera."""

import os

os.environ.setdefault("MUJOCO_GL", "osmesa")

import cv2
import numpy as np
import torch

from envisat_pose.geometry import EDGES
from envisat_pose.perception import batch_augment as ba
from envisat_pose.perception.data import DataConfig, augment_style, crop_box, crop_resize, line_targets, make_sample
from envisat_pose.perception.heatmaps import CORNER_JTYPE, encode_junctions


class Replay:
    """A stand-in generator for data.crop_box that returns given values in [-1, 1] for its uniform(-1, 1) draws."""

    def __init__(self, values):
        self.values = list(values)

    def uniform(self, lo, hi, size=None):
        assert (lo, hi) == (-1, 1)
        if size is None:
            return self.values.pop(0)
        return np.array([self.values.pop(0) for _ in range(size)])


def textured_frames(n, size, seed):
    """(n, size, size) uint8 frames with structure at all scales (blobs, edges, noise)."""
    rng = np.random.default_rng(seed)
    out = np.zeros((n, size, size), np.uint8)
    for k in range(n):
        coarse = rng.random((size // 8, size // 8)).astype(np.float32) * 255
        img = cv2.resize(coarse, (size, size), interpolation=cv2.INTER_CUBIC) + rng.normal(0, 12, (size, size))
        out[k] = np.clip(img, 0, 255).astype(np.uint8)
    return out


def random_labels(n, size, seed):
    """corners_px (n, 8, 2) rounded like the labels, visible and in_frame (n, 8): some corners outside."""
    rng = np.random.default_rng(seed)
    centre = rng.uniform(0.2, 0.8, (n, 1, 2)) * size
    corners = np.round(centre + rng.normal(0, 0.12 * size, (n, 8, 2)), 4)
    in_frame = np.all((corners >= -0.5) & (corners < size - 0.5), axis=-1)
    visible = in_frame & (rng.random((n, 8)) < 0.75)
    return corners, visible, in_frame


def tensors(*arrays):
    return [torch.from_numpy(np.ascontiguousarray(a)) for a in arrays]


def test_crop_boxes_follow_crop_box_exactly():
    cfg = DataConfig(input_px=96)
    corners, visible, in_frame = random_labels(200, 256, 1)
    in_frame[:10] = False  # no usable corner: the image centre
    rng = np.random.default_rng(2)
    u_scale, u_shift = rng.uniform(-1, 1, 200), rng.uniform(-1, 1, (200, 2))
    params = {"whole": torch.zeros(200, dtype=torch.bool), "u_scale": torch.from_numpy(u_scale),
              "u_shift": torch.from_numpy(u_shift)}
    c, f = tensors(corners, in_frame)
    got = ba.crop_boxes(c, f, (256, 256), cfg, params).numpy()
    plain = ba.crop_boxes(c, f, (256, 256), cfg, None).numpy()
    for n in range(200):
        want = crop_box(corners[n], in_frame[n], (256, 256), cfg, Replay([u_scale[n], *u_shift[n]]))
        assert np.array_equal(got[n], want), n
        assert np.array_equal(plain[n], crop_box(corners[n], in_frame[n], (256, 256), cfg, None)), n
    params["whole"][:5] = True
    assert (ba.crop_boxes(c, f, (256, 256), cfg, params)[:5] == torch.tensor([0, 0, 256])).all()


def test_crop_boxes_of_frames_of_several_sizes_follow_crop_box_at_each_size():
    """A mix of frame sizes (online looks at several resolutions): each sample's box is data.crop_box's at its own
    frame's size, the centre fallback and the whole frame included."""
    cfg = DataConfig(input_px=96)
    corners, visible, in_frame = random_labels(120, 128, 7)
    in_frame[:6] = False
    sides = np.resize([128, 256, 512], 120)
    rng = np.random.default_rng(8)
    u_scale, u_shift = rng.uniform(-1, 1, 120), rng.uniform(-1, 1, (120, 2))
    whole = np.zeros(120, bool)
    whole[[0, 1, 2, 50, 51, 52]] = True
    params = {"whole": torch.from_numpy(whole), "u_scale": torch.from_numpy(u_scale),
              "u_shift": torch.from_numpy(u_shift)}
    c, f = tensors(corners, in_frame)
    hw = torch.from_numpy(np.stack([sides, sides], 1).astype(np.int64))
    got = ba.crop_boxes(c, f, hw, cfg, params).numpy()
    for n in range(120):
        size = (int(sides[n]), int(sides[n]))
        if whole[n]:
            assert got[n].tolist() == [0, 0, size[0]], n
            continue
        want = crop_box(corners[n], in_frame[n], size, cfg, Replay([u_scale[n], *u_shift[n]]))
        assert np.array_equal(got[n], want), n


def test_crop_resize_matches_opencv_area_and_linear():
    frame = textured_frames(1, 300, 3)[0]
    rng = np.random.default_rng(4)
    boxes = np.array([[rng.integers(-80, 250), rng.integers(-80, 250), rng.integers(33, 420)] for _ in range(120)]
                     + [[0, 0, 300], [10, 20, 256], [5, 5, 64], [-40, 250, 128]])
    out = ba.crop_resize_batch(torch.from_numpy(frame)[None], torch.zeros(len(boxes), dtype=torch.int64),
                         torch.from_numpy(boxes), 128).numpy()
    diffs = []
    for k, box in enumerate(boxes):
        d = np.abs(out[k] - crop_resize(frame, box, 128).astype(np.float64))
        assert d.max() <= 1.0, box  # rounding of cv2's fixed-point bilinear weights: one level at most
        diffs.append((box[2] >= 128, d.mean()))
    shrink = [m for s, m in diffs if s]
    grow = [m for s, m in diffs if not s]
    assert max(shrink) < 0.01 and max(grow) < 0.25  # area weights: exact but for ties; bilinear: 11-bit weights


def test_evaluation_batch_equals_make_sample():
    """No jitter, no augmentation (make_sample with rng None): the image within one gray level, every target equal."""
    cfg = DataConfig(input_px=128)
    frames = textured_frames(6, 256, 5)
    corners, visible, in_frame = random_labels(6, 256, 6)
    corners[0, 3] = corners[0, 2] + 0.3  # two corners in one heatmap cell
    batch = ba.training_batch(*tensors(frames, corners, visible, in_frame), cfg, None)
    edges = {tuple(sorted(e)) for e in EDGES}
    for n in range(6):
        want = make_sample(frames[n], {"corners_px": corners[n], "visible": visible[n], "in_frame": in_frame[n]},
                           cfg, None)
        for key in ("jmap", "joff", "jmask", "corners_px", "valid", "crop_px"):
            assert np.array_equal(batch[key][n].numpy(), want[key]), key
        assert np.abs(batch["image"][n].numpy() - want["image"]).max() <= 1 / 255 / 0.25 + 1e-6
        # line targets: the same edges, as many segments, negatives from non-edge pairs of valid corners
        lab, wt, segs = (batch[k][n].numpy() for k in ("line_label", "line_weight", "segments_px"))
        assert np.array_equal(wt, want["line_weight"]) and np.array_equal(lab, want["line_label"])
        pos = want["line_label"] > 0
        assert np.array_equal(segs[pos], want["segments_px"][pos])
        valid_pts = want["corners_px"][want["valid"]]
        for seg in segs[(wt > 0) & (lab == 0)]:
            assert np.min(np.abs(valid_pts - seg[0]).sum(1)) == 0  # starts at a valid corner
            hit = np.flatnonzero(np.abs(want["corners_px"] - seg[1]).sum(1) == 0)
            if len(hit):  # a pair of corners: not an edge
                a = np.flatnonzero(np.abs(want["corners_px"] - seg[0]).sum(1) == 0)[0]
                assert tuple(sorted((int(a), int(hit[0])))) not in edges
            else:
                assert np.all((seg[1] >= 0) & (seg[1] <= 127))


def test_junction_targets_equal_numpy():
    rng = np.random.default_rng(7)
    points = rng.uniform(-10, 138, (64, 8, 2))
    points[:, 5] = points[:, 4] + rng.uniform(-1, 1, (64, 2))  # often the same cell
    points[3, 2] = np.nan
    valid = rng.random((64, 8)) < 0.8
    got = ba.encode_junctions_batch(torch.from_numpy(points), torch.from_numpy(valid), torch.from_numpy(CORNER_JTYPE),
                              (32, 32), 4, 1.0)
    for n in range(64):
        want = encode_junctions(points[n], valid[n], CORNER_JTYPE, (32, 32), 4, 1.0)
        for key in ("jmap", "joff", "jmask"):
            assert np.array_equal(got[key][n].numpy(), want[key]), (n, key)


def test_line_target_choices_have_the_numpy_statistics():
    """The random negatives and random segments: the same counts, pair frequencies and end-point spread."""
    corners, visible, in_frame = random_labels(1, 128, 8)
    corners, valid = corners[0], visible[0] & in_frame[0]
    valid[:] = [True, True, True, False, True, True, True, True]
    n = 2000
    c = torch.from_numpy(np.repeat(corners[None], n, 0))
    segs, lab, wt = ba.line_targets_batch(c, torch.from_numpy(np.repeat(valid[None], n, 0)),
                                    torch.Generator().manual_seed(9), 128)
    rng = np.random.default_rng(10)
    ref = [line_targets(corners, valid, rng, 128) for _ in range(n)]
    assert np.array_equal(wt.sum(1).numpy(), np.array([r[2].sum() for r in ref]))
    assert np.array_equal(lab.sum(1).numpy(), np.array([r[1].sum() for r in ref]))

    def stats(all_segs, all_lab, all_wt):
        """Share of segments starting at each corner and the mean free end point of random segments."""
        starts = np.zeros(8)
        ends = []
        for s, la, w in zip(all_segs, all_lab, all_wt):
            for seg in s[(w > 0) & (la == 0)]:
                starts[np.argmin(np.abs(corners - seg[0]).sum(1))] += 1
                if np.min(np.abs(corners - seg[1]).sum(1)) > 1e-3:
                    ends.append(seg[1])
        return starts / starts.sum(), np.mean(ends, 0), np.std(ends, 0), len(ends)

    a = stats(segs.numpy(), lab.numpy(), wt.numpy())
    b = stats(*(np.array([r[i] for r in ref]) for i in range(3)))
    assert np.abs(a[0] - b[0]).max() < 0.02
    assert a[3] == b[3]
    assert np.abs(a[1] - b[1]).max() < 3 * 37 / np.sqrt(a[3]) * 2 and np.abs(a[2] - b[2]).max() < 1.5


def test_style_augmentation_has_the_numpy_distributions():
    crop = textured_frames(1, 64, 11)[0]
    n = 600
    cfg = DataConfig(input_px=64)
    params = ba.draw_style_params(n, 64, torch.Generator().manual_seed(12))
    x = torch.from_numpy(np.repeat(crop[None], n, 0).astype(np.float32) / 255.0)
    got = ba.augment_style_batch(x, params).numpy()
    rng = np.random.default_rng(13)
    want = np.stack([augment_style(crop, rng) for _ in range(n)])
    assert cfg.input_px == got.shape[1] and got.dtype == np.float32 and got.min() >= 0 and got.max() <= 1
    for stat in (lambda a: a.mean((1, 2)), lambda a: a.std((1, 2)), lambda a: np.abs(np.diff(a, axis=2)).mean((1, 2)),
                 lambda a: (a >= 1.0).mean((1, 2))):
        s, t = stat(got), stat(want)
        se = np.sqrt(s.var() / n + t.var() / n)
        assert abs(s.mean() - t.mean()) < 4 * se + 1e-4, (s.mean(), t.mean(), se)
        assert np.abs(np.quantile(s, [0.1, 0.5, 0.9]) - np.quantile(t, [0.1, 0.5, 0.9])).max() < 12 * se + 2e-3


def test_training_batches_repeat_for_a_seed_and_differ_between_seeds():
    cfg = DataConfig(input_px=64)
    args = tensors(*(lambda c, v, f: (textured_frames(3, 128, 14), c, v, f))(*random_labels(3, 128, 15)))
    fs = torch.arange(3).repeat_interleave(4)
    a = ba.training_batch(*args, cfg, torch.Generator().manual_seed(1), fs)
    b = ba.training_batch(*args, cfg, torch.Generator().manual_seed(1), fs)
    c = ba.training_batch(*args, cfg, torch.Generator().manual_seed(2), fs)
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    assert not torch.equal(a["image"], c["image"]) and not torch.equal(a["crop_px"], c["crop_px"])
    assert len(set(map(tuple, a["crop_px"][:4].tolist()))) > 1  # a frame's crops each have their own box


# ---------------------------------------------------------------------------------------------------------
# A crop's labels against a render with the equivalent camera


def render_box(renderer, view, box, out_px):
    """The lit pass of `view` by the camera whose image is the square box (x0, y0, side) of the renderer's frame,
    at out_px: the frustum narrowed to the box (render_pixels.crop_frustum; intrinsics f' = f out/side,
    c' = (c - x0 + 0.5) out/side - 0.5). (out_px, out_px) float64 gray."""
    import mujoco

    from envisat_pose.datagen.render_pixels import crop_frustum

    renderer.set_view(view)
    renderer._gl.make_current()
    scn = renderer._scene
    mujoco.mjv_updateScene(renderer.model, renderer.data, renderer._opt, None, renderer._cam,
                           mujoco.mjtCatBit.mjCAT_ALL.value, scn)
    scn.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = renderer.shadows
    x0, y0, side = (int(v) for v in box)
    for c in scn.camera:
        c.frustum_center, c.frustum_width, c.frustum_bottom, c.frustum_top = crop_frustum(
            (x0, y0, x0 + side - 1, y0 + side - 1), renderer.resolution_px, c.frustum_bottom, c.frustum_top)
    rect = mujoco.MjrRect(0, 0, out_px, out_px)
    mujoco.mjr_render(rect, scn, renderer._con)
    rgb = np.empty((out_px, out_px, 3), np.uint8)
    mujoco.mjr_readPixels(rgb, None, rect, renderer._con)
    return cv2.flip(cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY), 0).astype(np.float64)


def displacement_px(a, b, iters=10):
    """(t (2,), e, centre (2,)): b(p) ~ a(p + t + e (p - centre)) by Gauss-Newton over the whole image (both
    smoothed by a Gaussian of 1 px): the shift and scale that bring a's pixels onto b's."""
    a = cv2.GaussianBlur(a.astype(np.float32), (0, 0), 1.0)
    b = cv2.GaussianBlur(b.astype(np.float32), (0, 0), 1.0)
    h, w = a.shape
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    c = np.array([(w - 1) / 2, (h - 1) / 2])
    p = np.zeros(3)
    for _ in range(iters):
        mx, my = xx + p[0] + p[2] * (xx - c[0]), yy + p[1] + p[2] * (yy - c[1])
        aw = cv2.remap(a, mx.astype(np.float32), my.astype(np.float32), cv2.INTER_CUBIC,
                       borderMode=cv2.BORDER_REPLICATE)
        gx, gy = cv2.Sobel(aw, cv2.CV_32F, 1, 0, ksize=3) / 8, cv2.Sobel(aw, cv2.CV_32F, 0, 1, ksize=3) / 8
        J = np.stack([gx, gy, gx * (xx - c[0]) + gy * (yy - c[1])], -1)[4:-4, 4:-4].reshape(-1, 3)
        p += np.linalg.lstsq(J.astype(np.float64), (b - aw)[4:-4, 4:-4].ravel().astype(np.float64), rcond=None)[0]
    return p[:2], p[2], c


def test_crop_moves_labels_as_the_equivalent_camera_sees_them():
    """Render a 512 px frame, crop and shrink it with the batched op (the crop rule's margins, off centre), and
    render the same view with the camera whose image is that crop (4x supersampled, area-averaged by 4: an image
    independent of the op). The crop's pixels sit on the equivalent camera's within 0.05 px at every corner
    (shift and scale fitted over the image), and the label moved by to_input_px is that camera's projection."""
    from envisat_pose.attitude import quat_to_rotmat
    from envisat_pose.datagen.labels import project_px
    from envisat_pose.datagen.render import SceneRenderer
    from envisat_pose.datagen.render_view import View

    renderer = SceneRenderer(512)
    rng = np.random.default_rng(21)
    s_px = 128
    worst, shifts = 0.0, []
    try:
        for range_m in (33.0, 42.0, 51.0):
            q = rng.standard_normal(4)
            view = View(np.array([rng.uniform(-2, 2), range_m, rng.uniform(-2, 2)]),
                        quat_to_rotmat(q / np.linalg.norm(q)), np.array([-0.3, -1.0, 0.4]) + rng.normal(0, 0.3, 3))
            out = renderer.render(view)
            corners = project_px(out.corners_K_m, renderer.K)
            lo, hi = corners.min(0), corners.max(0)
            for margin in (1.25, 1.6):
                side = int(np.ceil((hi - lo).max() * margin))
                centre = (lo + hi) / 2 + rng.uniform(-0.1, 0.1, 2) * side
                # the crop inside the frame (the equivalent camera sees beyond it, the frame's crop does not)
                box = np.array([*np.clip(np.round(centre - side / 2).astype(int), 0, 512 - side), side])
                a = ba.crop_resize_batch(torch.from_numpy(out.gray_u8)[None], torch.zeros(1, dtype=torch.int64),
                                   torch.from_numpy(box)[None], s_px)[0].numpy()
                b = cv2.resize(render_box(renderer, view, box, 4 * s_px), (s_px, s_px), interpolation=cv2.INTER_AREA)
                t, e, c = displacement_px(a, b)
                labels_in = ba.to_input_px_batch(torch.from_numpy(corners)[None], torch.from_numpy(box)[None], s_px)[0]
                k2 = renderer.K.copy()
                k2[:2] *= s_px / side
                k2[:2, 2] = (renderer.K[:2, 2] - box[:2] + 0.5) * s_px / side - 0.5
                assert np.abs(labels_in.numpy() - project_px(out.corners_K_m, k2)).max() < 1e-9
                moved = t[None] + e * (labels_in.numpy() - c)  # the image's displacement at each corner
                worst = max(worst, float(np.abs(moved).max()))
                shifts.append(t)
    finally:
        renderer.close()
    assert worst < 0.05, worst
    assert np.abs(np.mean(shifts, 0)).max() < 0.02  # no systematic offset
