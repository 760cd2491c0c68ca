"""The image factory end to end: shard contract, determinism across runs, workers and backends, resume after
kill -9, verification, bad configs, corruption replay, sequence mode."""

import os

os.environ.setdefault("MUJOCO_GL", "osmesa")

import json
import shutil
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from envisat_pose.app.cli import main as envisat_main
from envisat_pose.attitude import mrp_to_dcm
from envisat_pose.config import from_dict
from envisat_pose.datagen.dataset import verify_dataset
from envisat_pose.datagen.factory import run_generate
from envisat_pose.datagen.generate_config import GenerateConfig, config_from_json
from envisat_pose.datagen.shards import decode_png
from envisat_pose.datagen.views import sample_random_view
from envisat_pose.shard_reader import load_dataset_manifest, read_shard

ENVISAT = [sys.executable, "-m", "envisat_pose.app.cli"]


def small_cfg(**kw):
    base = {"num_images": 6, "shard_size": 2, "resolution_px": 128, "seed": 5, "earth_probability": 0.3}
    base.update(kw)
    return from_dict(GenerateConfig, base)


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """An uninterrupted single-worker run, the bytes every other run must reproduce."""
    out = str(tmp_path_factory.mktemp("ref") / "ds")
    manifest = run_generate(small_cfg(), out)
    return out, manifest


def shas(manifest):
    return [(e["name"], e["sha256"], e["count"]) for e in manifest["shards"]]


def test_shard_contract(reference):
    out, manifest = reference
    assert manifest["complete"] and manifest["num_shards"] == 3 and manifest["root_seed"] == 5
    assert manifest["config"]["resolution_px"] == 128
    import webdataset as wds

    urls = [os.path.join(out, e["name"]) for e in manifest["shards"]]
    samples = list(wds.WebDataset(urls, shardshuffle=False))
    assert len(samples) == 6
    for s in samples:
        assert {"png", "mask.png", "depth.png", "json"} <= set(s)
        lab = json.loads(s["json"])
        for name, shape in (("corners_px", (8, 2)), ("visible", (8,)), ("in_frame", (8,)), ("x", (12,)),
                            ("K", (3, 3)), ("R_cam_from_target", (3, 3)), ("t_cam_from_target_m", (3,))):
            assert np.array(lab[name]).shape == shape, name
        assert {"depth_scale_m", "corruption", "seed"} <= set(lab)
        img, mask, depth = decode_png(s["png"]), decode_png(s["mask.png"]), decode_png(s["depth.png"])
        assert img.dtype == np.uint8 and img.shape == (128, 128)
        assert depth.dtype == np.uint16 and mask.dtype == np.uint8
        assert set(np.unique(mask)) <= set(range(9))  # 8: the clutter (appendages)
        assert np.array_equal(depth > 0, mask > 0)  # 0 is background in both
        R = np.array(lab["R_cam_from_target"])
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-9)
        # the pose in the camera frame is the state's: R = R_K_from_C Gamma(p)^T, t = R_K_from_C rho
        x = np.array(lab["x"])
        R_K_from_C = np.array([[0.0, 0.0, -1.0], [-1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
        np.testing.assert_allclose(R, R_K_from_C @ mrp_to_dcm(x[6:9]).T, atol=1e-9)
        np.testing.assert_allclose(lab["t_cam_from_target_m"], R_K_from_C @ x[0:3], atol=1e-8)
        K = np.array(lab["K"])
        assert K[0, 2] == K[1, 2] == 63.5 and abs(K[0, 0] - 64 / np.tan(np.radians(15))) < 1e-6
        # the range in the depth image agrees with the pose: the CoM lies inside the body, behind its surface
        z_com = lab["t_cam_from_target_m"][2]
        if mask.any():
            d_m = depth[depth > 0] * lab["depth_scale_m"]
            assert d_m.min() < z_com + 1.2 and d_m.max() > z_com - 23.0


def test_same_seed_same_manifest(reference, tmp_path):
    out, manifest = reference
    again = run_generate(small_cfg(), str(tmp_path / "again"))
    assert again == manifest
    other = run_generate(small_cfg(seed=6), str(tmp_path / "other"))
    assert shas(other) != shas(manifest)


def test_dask_two_workers_same_bytes(reference, tmp_path):
    _, manifest = reference
    dask = run_generate(small_cfg(), str(tmp_path / "dask"), workers=2, backend="dask")
    assert shas(dask) == shas(manifest)


def test_existing_dask_scheduler_by_address(reference, tmp_path):
    """--backend dask --scheduler ADDRESS: the CLI submits to a running cluster (here one on 127.0.0.1)."""
    from dask.distributed import LocalCluster

    _, manifest = reference
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=True, host="127.0.0.1",
                      dashboard_address=None) as cluster:
        assert cluster.scheduler_address.startswith("tcp://127.0.0.1:")
        rc = envisat_main(["generate", "--num-images", "6", "--shard-size", "2", "--resolution", "128", "--seed",
                           "5", "--out", str(tmp_path / "ds"), "--backend", "dask", "--scheduler",
                           cluster.scheduler_address, "--quiet", "--config", str(write_earth_config(tmp_path))])
    assert rc == 0
    assert shas(load_dataset_manifest(str(tmp_path / "ds"))) == shas(manifest)


def write_earth_config(tmp_path):
    path = tmp_path / "gen.toml"
    path.write_text("earth_probability = 0.3\n")
    return path


def test_process_pool_two_workers_same_bytes(reference, tmp_path):
    _, manifest = reference
    pool = run_generate(small_cfg(), str(tmp_path / "pool"), workers=2)
    assert shas(pool) == shas(manifest)


def test_kill_then_resume_gives_the_uninterrupted_bytes(tmp_path):
    args = ["generate", "--mode", "random", "--num-images", "40", "--shard-size", "2", "--resolution", "256",
            "--seed", "9", "--out", str(tmp_path / "ds"), "--quiet"]
    ref = run_generate(from_dict(GenerateConfig, {"num_images": 40, "shard_size": 2, "resolution_px": 256,
                                                  "seed": 9}), str(tmp_path / "ref"))
    proc = subprocess.Popen(ENVISAT + args, cwd=os.path.dirname(os.path.dirname(os.path.dirname(__file__))))
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:
        m = load_dataset_manifest(str(tmp_path / "ds")) if (tmp_path / "ds" / "manifest.json").exists() else None
        if m is not None and len(m["shards"]) >= 3:
            break
        time.sleep(0.005)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    killed = load_dataset_manifest(str(tmp_path / "ds"))
    assert not killed["complete"], "the run finished before the kill: the test did not interrupt it"
    assert envisat_main(["dataset", "verify", str(tmp_path / "ds")]) == 1
    assert envisat_main(args) == 0
    resumed = load_dataset_manifest(str(tmp_path / "ds"))
    assert resumed == ref
    assert envisat_main(["dataset", "verify", str(tmp_path / "ds")]) == 0
    files = sorted(os.listdir(tmp_path / "ds"))
    assert files == sorted(["manifest.json", "generate.config.toml"] + [e["name"] for e in ref["shards"]])


def test_resume_redoes_a_damaged_shard(reference, tmp_path, capsys):
    src, manifest = reference
    out = str(tmp_path / "ds")
    shutil.copytree(src, out)
    victim = os.path.join(out, manifest["shards"][1]["name"])
    with open(victim, "r+b") as fh:
        fh.seek(700)
        fh.write(b"\x00garbage\x00")
    assert envisat_main(["dataset", "verify", out]) == 1
    assert "shard-000001.tar: sha256 " in capsys.readouterr().out
    os.truncate(os.path.join(out, manifest["shards"][2]["name"]), 1000)  # a partial file
    assert run_generate(small_cfg(), out) == manifest
    assert envisat_main(["dataset", "verify", out]) == 0


def test_a_rerun_of_a_finished_dataset_reads_each_shard_once(reference, tmp_path, monkeypatch):
    """A rerun hashed every shard twice (the job's sha256 check, then the shard check's own): a terabyte dataset's
    resume read two terabytes. Once each now, and a shard of the right bytes but a tampered count is still redone."""
    import envisat_pose.io as io
    import envisat_pose.resumable as resumable
    import envisat_pose.shard_reader as shard_reader

    src, manifest = reference
    out = str(tmp_path / "ds")
    shutil.copytree(src, out)
    hashed = []

    def counted(path):
        hashed.append(os.path.basename(path))
        return io.sha256_file(path)

    for module in (resumable, shard_reader):
        monkeypatch.setattr(module, "sha256_file", counted)
    assert run_generate(small_cfg(), out) == manifest
    assert sorted(hashed) == sorted(e["name"] for e in manifest["shards"])
    with open(os.path.join(out, "manifest.json")) as fh:
        told = json.load(fh)
    told["shards"][1]["count"] = 3  # its bytes as written, its count not theirs: the walk of its headers says so
    with open(os.path.join(out, "manifest.json"), "w") as fh:
        json.dump(told, fh)
    victim = os.path.join(out, manifest["shards"][1]["name"])
    before = os.stat(victim).st_ino
    assert run_generate(small_cfg(), out) == manifest and os.stat(victim).st_ino != before  # redone


def test_verify_reports_a_missing_shard(reference, tmp_path, capsys):
    src, manifest = reference
    out = str(tmp_path / "ds")
    shutil.copytree(src, out)
    os.remove(os.path.join(out, manifest["shards"][0]["name"]))
    assert envisat_main(["dataset", "verify", out]) == 1
    assert "shard-000000.tar: missing" in capsys.readouterr().out


def test_verify_reports_a_partial_file_in_a_folder_named_with_glob_characters(tmp_path):
    out = tmp_path / "set [v1]"  # '[v1]' is a glob character class: the folder's name must be taken literally
    out.mkdir()
    (out / "manifest.json").write_text(json.dumps({"complete": True, "num_images": 0, "num_shards": 0, "shards": []}))
    (out / ".tmp-123-shard-000000.tar-x").write_bytes(b"half a shard")
    assert verify_dataset(str(out)) == [".tmp-123-shard-000000.tar-x: partial file of an interrupted run"]


@pytest.mark.parametrize("flags, message", [
    (["--num-images", "0"], "--num-images 0"),  # named as the flag typed
    (["--resolution", "0"], "--resolution 0"),
    (["--mode", "spiral"], "--mode 'spiral'"),
])
def test_bad_config_clear_error_nothing_written(tmp_path, capsys, flags, message):
    out = tmp_path / "ds"
    rc = envisat_main(["generate", "--out", str(out), "--num-images", "4", "--resolution", "64"] + flags)
    err = capsys.readouterr().err
    assert rc == 2 and message in err and len(err.strip().splitlines()) == 1
    assert not out.exists()


def test_unwritable_output_clear_error(tmp_path, capsys):
    blocker = tmp_path / "a_file"
    blocker.write_text("x")
    rc = envisat_main(["generate", "--out", str(blocker / "ds"), "--num-images", "2", "--resolution", "64"])
    err = capsys.readouterr().err
    assert rc == 2 and "'a_file' is a file, not a folder" in err.replace(str(tmp_path) + "/", "")
    assert sorted(os.listdir(tmp_path)) == ["a_file"]
    rc = envisat_main(["generate", "--out", str(blocker), "--num-images", "2", "--resolution", "64"])
    assert rc == 2 and "not a folder" in capsys.readouterr().err
    assert blocker.read_text() == "x"


@pytest.mark.parametrize("out", ["/proc/envisat-test-ds", "/proc/self/envisat-test-ds", "/sys/envisat-test-ds"])
def test_output_where_nothing_can_be_created_is_one_error_line(out, capsys):
    """The parent exists but refuses new entries even to root (os.access says yes to root): the factory must
    try the write and report it, not end in a traceback."""
    rc = envisat_main(["generate", "--out", out, "--num-images", "2", "--resolution", "64", "--quiet"])
    err = capsys.readouterr().err
    assert rc == 2, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and out in lines[0] and "cannot write there" in lines[0], err
    assert not os.path.exists(out)


def test_montage_is_written_atomically_and_unwritable_montage_is_one_line(reference, tmp_path, capsys, monkeypatch):
    import cv2

    out, _ = reference
    target = tmp_path / "m.png"
    target.write_bytes(b"old montage")

    def interrupted_rename(src, dst):  # the job is killed just before the temp file would replace the old one
        raise KeyboardInterrupt

    with monkeypatch.context() as mp:
        mp.setattr(os, "replace", interrupted_rename)
        assert envisat_main(["dataset", "inspect", out, "--montage", str(target), "--count", "2"]) == 130
    assert target.read_bytes() == b"old montage"  # never a half-written file under the final name
    assert sorted(os.listdir(tmp_path)) == ["m.png"]  # and no temp file left behind
    assert envisat_main(["dataset", "inspect", out, "--montage", str(target), "--count", "2"]) == 0
    assert cv2.imread(str(target)).shape == (256, 512, 3)
    assert sorted(os.listdir(tmp_path)) == ["m.png"]
    capsys.readouterr()
    assert envisat_main(["dataset", "inspect", out, "--montage", "/proc/envisat-montage.png", "--count", "2"]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "/proc/envisat-montage.png" in err, err


def test_other_config_in_out_dir_is_refused(reference, tmp_path, capsys):
    src, _ = reference
    out = str(tmp_path / "ds")
    shutil.copytree(src, out)
    before = {f: os.path.getmtime(os.path.join(out, f)) for f in os.listdir(out)}
    rc = envisat_main(["generate", "--out", out, "--num-images", "6", "--shard-size", "2", "--resolution", "128",
                       "--seed", "99"])
    assert rc == 2 and "another config or seed" in capsys.readouterr().err
    assert before == {f: os.path.getmtime(os.path.join(out, f)) for f in os.listdir(out)}


def test_label_replays_the_sample(reference):
    """A label alone reproduces its image: its seed replays the pose, its scene renders the same clean image
    (appearance, lights and clutter included), its corruption parameters turn that into the stored bytes."""
    from envisat_pose.datagen.corrupt import apply_corruption
    from envisat_pose.datagen.factory import view_from_scene
    from envisat_pose.datagen.render import SceneRenderer

    out, manifest = reference
    cfg = config_from_json(json.dumps(manifest["config"]))
    assert cfg.appearance_on and cfg.appendages_on  # the defaults of random mode
    r = SceneRenderer(cfg.resolution_px, texture_set_size=cfg.appearance.texture_set_size)
    try:
        n_corrupted = 0
        for key, members in read_shard(os.path.join(out, manifest["shards"][1]["name"])):
            lab = json.loads(members["json"])
            _, x, _ = sample_random_view(cfg, r.fovy_deg, np.random.default_rng(lab["seed"]))
            np.testing.assert_allclose(x, lab["x"], atol=1e-9)
            assert lab["scene"]["look"]["materials"]["face_py"]["class"] == "mli_gold"
            clean = r.render(view_from_scene(lab["scene"])).gray_u8
            stored = decode_png(members["png"])
            assert np.array_equal(apply_corruption(clean, lab["corruption"]), stored)
            n_corrupted += not np.array_equal(clean, stored)
        assert n_corrupted >= 1
    finally:
        r.close()


def test_sequence_mode_follows_the_truth(tmp_path):
    from envisat_pose.datagen.scenario import scenario_config
    from envisat_pose.datagen.truth import simulate_truth

    cfg = from_dict(GenerateConfig, {"mode": "sequence", "num_images": 4, "shard_size": 3, "resolution_px": 128,
                                     "seed": 2, "sequence": {"frame_dt_s": 5.0}})
    manifest = run_generate(cfg, str(tmp_path / "seq"))
    labels = [json.loads(m["json"]) for e in manifest["shards"]
              for _, m in read_shard(os.path.join(tmp_path / "seq", e["name"]))]
    truth = simulate_truth(scenario_config("default", duration_s=15.0, dt_s=5.0, seed=2))
    assert [lab["scene"]["t_s"] for lab in labels] == [0.0, 5.0, 10.0, 15.0]
    # independent paths to the same pixels: the truth projects MuJoCo's corner sites through its camera in the
    # inertial world at 1024 px; the label projects the render world's corners through K at 128 px
    scale = 128 / 1024
    expected_px = (truth.corners_px[:4] + 0.5) * scale - 0.5
    np.testing.assert_allclose([lab["corners_px"] for lab in labels], expected_px, atol=1e-3)
    assert np.ptp(expected_px[:, 0], axis=0).max() > 1.0  # the tumble moves the corners: frames are told apart
    # the default V-bar hold: target 50 m down the boresight, all corners in frame
    for lab in labels:
        assert abs(lab["t_cam_from_target_m"][2] - 50.0) < 0.5 and all(lab["in_frame"])


def test_inspect_prints_stats_and_writes_a_montage(reference, tmp_path, capsys):
    import cv2

    out, manifest = reference
    montage = tmp_path / "m.png"
    assert envisat_main(["dataset", "inspect", out, "--montage", str(montage), "--count", "4"]) == 0
    text = capsys.readouterr().out
    stats = json.loads(text[: text.rindex("}") + 1])
    assert stats["samples"] == 6 and sum(stats["visible_keypoints_histogram"]) == 6
    assert 20.0 <= stats["range_m"]["min"] <= stats["range_m"]["max"] <= 80.0  # range_min_m, range_max_m
    img = cv2.imread(str(montage))
    assert img.shape == (512, 512, 3)
    # labelled corners are drawn in colour on the grey renders
    assert np.any((img[..., 1] > 150) & (img[..., 0] < 80) & (img[..., 2] < 80))
