"""`envisat track` on what users have: a generate folder, PNG folders (--rate-hz, --timestamps), a video, a
512 px sequence with its own camera file; frames whose labels were removed; bad inputs as one line with nothing
written. The frames are MuJoCo renders of the default scenario (envisat generate --mode sequence)."""

import json
import os

import numpy as np
import pytest

from envisat_pose.app.cli import main


def generate(out, n, seed=7, resolution=None):
    args = ["generate", "--mode", "sequence", "--scenario", "default", "--num-images", str(n), "--seed", str(seed),
            "--workers", "1", "--out", str(out), "--quiet"]
    if resolution:
        args += ["--resolution", str(resolution)]
    assert main(args) == 0
    return out


@pytest.fixture(scope="module")
def seq_dir(tmp_path_factory):
    return generate(tmp_path_factory.mktemp("seq") / "gen", 90)


def as_pngs(gen_dir, out):
    """A generate folder's frames as plain PNG files, labels removed (names sort in time order)."""
    import cv2

    from envisat_pose.datagen.dataset import iter_samples, sample_image

    out.mkdir(parents=True, exist_ok=True)
    for i, (key, label, members) in enumerate(iter_samples(str(gen_dir))):
        cv2.imwrite(str(out / f"img_{i:04d}.png"), sample_image(members, label))
    return out


@pytest.fixture(scope="module")
def png_dir(seq_dir, tmp_path_factory):
    """The module's sequence as plain PNG files, labels removed."""
    return as_pngs(seq_dir, tmp_path_factory.mktemp("png"))


@pytest.fixture(scope="module")
def three_pngs(tmp_path_factory):
    """Three frames as plain PNG files: all the bad-input checks need (the fast lane's; the 90-frame sequence is
    the slow tests')."""
    base = tmp_path_factory.mktemp("three")
    return as_pngs(generate(base / "gen", 3), base / "png")


def est_errors(run_dir, truth_x):
    from envisat_pose.contracts import Estimates
    from envisat_pose.state import error_magnitudes

    est = Estimates.load(str(run_dir / "est.npz"))
    return est, error_magnitudes(truth_x, est.x_hat[0])


def truth_of(seq_dir):
    from envisat_pose.datagen.dataset import iter_samples

    return np.array([label["x"] for _, label, _ in iter_samples(str(seq_dir))])


@pytest.mark.slow
def test_frames_without_labels_converge_from_a_cold_start(png_dir, seq_dir, tmp_path, detector_weights):
    """The shipped weights on PNGs with no labels: acquiring, then tracking, within 10 cm and 1 deg at the end;
    no truth in the outputs (x_true absent, no error plot)."""
    out = tmp_path / "run"
    assert main(["track", "--images", str(png_dir), "--rate-hz", "1", "--out", str(out), "--quiet",
                 "--weights", detector_weights]) == 0
    est, err = est_errors(out, truth_of(seq_dir))
    assert np.isnan(est.x_true).all() and not (out / "errors.png").exists()
    summary = json.loads((out / "summary.json").read_text())
    assert summary["final_status"] == "tracking" and summary["first_tracking_s"] <= 40.0, summary
    assert err["position_m"][-10:].max() < 0.10 and err["attitude_deg"][-10:].max() < 1.0, \
        (err["position_m"][-10:], err["attitude_deg"][-10:])
    assert {"est.npz", "det.npz", "track.config.toml", "summary.json", "recording.rrd"} <= set(os.listdir(out))


def test_a_generate_folder_is_tracked_and_scored(seq_dir, tmp_path, detector_weights, capsys):
    out = tmp_path / "gen"
    assert main(["track", "--images", str(seq_dir), "--out", str(out), "--quiet", "--weights", detector_weights]) == 0
    est, _ = est_errors(out, truth_of(seq_dir))
    np.testing.assert_array_equal(est.x_true[0], truth_of(seq_dir))
    summary = json.loads((out / "summary.json").read_text())
    assert "scores" in summary and (out / "errors.png").exists()
    import hashlib  # the weights by sha256 beside their path (the path alone did not say which weights tracked)

    assert summary["weights_sha256"] == hashlib.sha256(open(detector_weights, "rb").read()).hexdigest()
    printed = capsys.readouterr().out
    assert "false-lock time" in printed and "first track correct" in printed


def test_timestamps_and_a_video(png_dir, tmp_path, detector_weights):
    """--timestamps (file,t_s) gives the times; a video written by OpenCV is read at --rate-hz."""
    import cv2

    files = sorted(os.listdir(png_dir))[:25]
    sub = tmp_path / "sub"
    sub.mkdir()
    for f in files:
        os.link(png_dir / f, sub / f)
    csv = tmp_path / "times.csv"
    csv.write_text("file,t_s\n" + "".join(f"{f},{10.0 + 2 * i}\n" for i, f in enumerate(files)))
    out = tmp_path / "ts"
    assert main(["track", "--images", str(sub), "--timestamps", str(csv), "--out", str(out), "--quiet",
                 "--weights", detector_weights]) == 0
    with np.load(out / "est.npz") as z:
        np.testing.assert_allclose(z["t_s"], 10.0 + 2 * np.arange(25))
    video = tmp_path / "seq.avi"
    w = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 1.0, (1024, 1024), isColor=True)
    for f in files[:20]:  # the cold start's minimum (TrackerConfig.acquire.frames)
        w.write(cv2.cvtColor(cv2.imread(str(sub / f), cv2.IMREAD_GRAYSCALE), cv2.COLOR_GRAY2BGR))
    w.release()
    out = tmp_path / "vid"
    assert main(["track", "--images", str(video), "--rate-hz", "2", "--out", str(out), "--quiet",
                 "--weights", detector_weights]) == 0
    with np.load(out / "det.npz") as z:
        np.testing.assert_allclose(z["t_s"], np.arange(20) / 2.0)
        assert z["visible"].sum(axis=1).max() >= 4  # the detector found the target in the decoded frames


@pytest.fixture(scope="module")
def track_512(tmp_path_factory, detector_weights):
    """Frames of another size with a camera file (the MJCF's field of view at 512 px, written as fx, fy, cx, cy)
    tracked: (the output folder, the frames' truth (T, 12))."""
    from envisat_pose.geometry import load_camera

    base = tmp_path_factory.mktemp("t512")
    # 120 frames: 20 for the cold start's window, then the bank's confirmation (the half-turn decided by the
    # dynamics as well as the appearance: on this sequence the two disagree until the twin's dynamics fail, and
    # the truth is claimed from frame 94; then 26 frames of margin)
    seq = generate(base / "g512", 120, seed=3, resolution=512)
    cam = load_camera().scaled(512, 512)
    camfile = base / "cam.toml"
    camfile.write_text(f"fx = {cam.f_px}\nfy = {cam.f_px}\ncx = {cam.cu_px}\ncy = {cam.cv_px}\nwidth = 512\nheight = 512\n")
    out = base / "t512"
    assert main(["track", "--images", str(seq), "--camera", str(camfile), "--out", str(out), "--quiet",
                 "--weights", detector_weights]) == 0
    return out, truth_of(seq)


def test_a_512_px_sequence_with_its_own_camera(track_512):
    """The tracker's pixel model is the file's camera: on every frame it claims tracking, its position is within
    1 % of the range of the truth's (the frames' labels), along the line of sight (range) and across it. A camera
    not taken from the file shows there: the focal length 2 % off puts the range 0.8 m (1.6 %) off on this
    sequence; the file's camera leaves 0.2 m (the detector's apparent scale at 512 px)."""
    from envisat_pose.state import POS

    out, truth_x = track_512
    summary = json.loads((out / "summary.json").read_text())
    assert summary["frames_by_status"]["tracking"] >= 1, summary
    est, err = est_errors(out, truth_x)
    np.testing.assert_array_equal(est.x_true[0], truth_x)
    claimed = est.status[0] == 1
    r_true = np.linalg.norm(truth_x[claimed][:, POS], axis=1)
    r_hat = np.linalg.norm(est.x_hat[0, claimed][:, POS], axis=1)
    assert np.all(np.abs(r_hat - r_true) < 0.01 * r_true), r_hat - r_true
    assert np.all(err["position_m"][claimed] < 0.01 * r_true), err["position_m"][claimed]


def test_the_512_px_track_claims_the_truths_attitude(track_512):
    """Every frame claimed tracking is within 5 deg of the truth's attitude (the project's false-lock bound). On
    this sequence the bank once dropped the truth on the dynamics' evidence (the detector's repeated errors)
    while the detector's appearance favoured it by 9-10 nats, and claimed the half-turn twin 179.8 deg off on
    every frame it called tracking; the appearance veto (bank.appearance_veto) keeps the truth open."""
    out, truth_x = track_512
    est, err = est_errors(out, truth_x)
    claimed = est.status[0] == 1
    assert claimed.any() and np.all(err["attitude_deg"][claimed] < 5.0), err["attitude_deg"][claimed]


def bad(args, capsys, tmp_path):
    out = tmp_path / "never"
    code = main(["track", *args, "--out", str(out), "--quiet"])
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1, err
    assert not out.exists(), "a bad input must leave nothing written"
    return err


def test_bad_inputs_are_one_line_and_write_nothing(three_pngs, tmp_path, capsys):
    import cv2

    empty = tmp_path / "empty"
    empty.mkdir()
    assert "no image files" in bad(["--images", str(empty), "--rate-hz", "1"], capsys, tmp_path)
    # an unreadable (truncated) image among good ones
    broken = tmp_path / "broken"
    broken.mkdir()
    good = sorted(os.listdir(three_pngs))[:3]
    for f in good:
        os.link(three_pngs / f, broken / f)
    data = (three_pngs / good[0]).read_bytes()
    (broken / "img_9999.png").write_bytes(data[: len(data) // 2])
    assert "img_9999.png" in bad(["--images", str(broken), "--rate-hz", "1"], capsys, tmp_path)
    # frames of mixed sizes
    mixed = tmp_path / "mixed"
    mixed.mkdir()
    for f in good:
        os.link(three_pngs / f, mixed / f)
    cv2.imwrite(str(mixed / "img_9999.png"), np.zeros((512, 512), np.uint8))
    assert "img_9999.png" in bad(["--images", str(mixed), "--rate-hz", "1"], capsys, tmp_path)
    # timestamps not increasing, and missing a file
    sub = tmp_path / "three"
    sub.mkdir()
    for f in good:
        os.link(three_pngs / f, sub / f)
    csv = tmp_path / "t.csv"
    csv.write_text("file,t_s\n" + "".join(f"{f},{5 - i}\n" for i, f in enumerate(good)))
    assert "increase" in bad(["--images", str(sub), "--timestamps", str(csv)], capsys, tmp_path)
    csv.write_text("file,t_s\n" + "".join(f"{f},{i}\n" for i, f in enumerate(good[:2])))
    assert good[2] in bad(["--images", str(sub), "--timestamps", str(csv)], capsys, tmp_path)
    # a folder of images without a rate
    assert "--rate-hz" in bad(["--images", str(sub)], capsys, tmp_path)
    # camera files: fx missing, a non-positive focal length
    cam = tmp_path / "cam.toml"
    cam.write_text("fy = 1910.0\ncx = 511.5\ncy = 511.5\nwidth = 1024\nheight = 1024\n")
    assert "'fx'" in bad(["--images", str(sub), "--rate-hz", "1", "--camera", str(cam)], capsys, tmp_path)
    cam.write_text("fx = -3.0\nfy = 1910.0\ncx = 511.5\ncy = 511.5\nwidth = 1024\nheight = 1024\n")
    assert "fx = -3.0" in bad(["--images", str(sub), "--rate-hz", "1", "--camera", str(cam)], capsys, tmp_path)
    # a video that cannot be opened
    fake = tmp_path / "clip.mp4"
    fake.write_bytes(b"not a video at all")
    assert "clip.mp4" in bad(["--images", str(fake), "--rate-hz", "1"], capsys, tmp_path)


def test_a_sequence_in_the_earths_shadow_has_no_lit_frame(tmp_path, capsys):
    """ENVISAT's slow tumble at seed 3 starts in the shadow with the seed's sun (generate warns): scored with its
    truth, its first lit frame is none (it was said to be 0 s, the first frame, as every frame has an image) and
    nothing is claimed."""
    data, out = str(tmp_path / "dark"), tmp_path / "track"
    assert main(["generate", "--mode", "sequence", "--scenario", "slow-tumble", "--seed", "3", "--num-images", "20",
                 "--resolution", "64", "--out", data, "--quiet"]) == 0
    assert "20 of 20 frames are in the Earth's shadow" in capsys.readouterr().err
    assert main(["track", "--images", data, "--out", str(out), "--quiet"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    run = summary["scores"]["per_run"][0]
    assert run["first_lit_s"] is None and run["first_tracking_s"] is None and run["false_lock_frames"] == 0
    assert summary["camera"]["default"] is True and summary["camera"]["file"] is None
    # a PinholeCamera a caller gives is not the default one (it was recorded as such)
    from envisat_pose.geometry import load_camera
    from envisat_pose.pipelines.runs.track import TrackConfig, track_frames

    own = track_frames(TrackConfig(scenario="slow-tumble"), data, camera=load_camera().scaled(64, 64),
                       out_dir=str(tmp_path / "own"))
    assert own["camera"]["default"] is False and own["camera"]["file"] is None and own["camera"]["width_px"] == 64
