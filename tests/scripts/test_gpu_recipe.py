"""The GPU recipe's parts that run without a GPU: the package laid out without a build (scripts/gpu_layout.py)
imports from its own folder, finds its data and loads the gravity plugin through the entry point; the data plan
of a leg (scripts/gpu_train.py) is a set of valid generate configs with the mix the issue asks for."""

import importlib.util
import os
import subprocess
import sys

import numpy as np
import pytest

os.environ.setdefault("MUJOCO_GL", "osmesa")

from envisat_pose import named_scenarios  # noqa: E402
from envisat_pose.config import resolve_job_config  # noqa: E402
from envisat_pose.datagen.generate_config import GenerateConfig  # noqa: E402

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def script(name):
    spec = importlib.util.spec_from_file_location(name, os.path.join(ROOT, "scripts", f"{name}.py"))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_laid_out_package_imports_from_its_folder_and_loads_the_plugin(tmp_path):
    dest = tmp_path / "pkg"
    info = script("gpu_layout").lay_out(str(dest))
    assert info["plugin"].startswith("_relative_gravity")
    probe = ("import json, envisat_pose, mujoco\n"
             "from importlib import metadata, resources\n"
             "from envisat_pose.datagen import plugin\n"
             "from envisat_pose import named_scenarios\n"
             "from envisat_pose.provenance import git_hash\n"
             "eps = [e for e in metadata.entry_points(group='mujoco.plugins') if e.name == 'envisat_relative_gravity']\n"
             "print(json.dumps({'pkg': envisat_pose.__file__, 'lib': plugin._HANDLES[0]._name if plugin._HANDLES else None,"
             " 'mjcf': str(resources.files('envisat_pose.models')), 'scenarios': named_scenarios.names(),"
             " 'git': git_hash(), 'entry': [e.value for e in eps], 'cli': metadata.entry_points(group='console_scripts')['envisat'].value}))\n")
    env = {**os.environ, "PYTHONPATH": str(dest), "MUJOCO_GL": "osmesa", "ENVISAT_SOURCE_GIT": "0123abc"}
    proc = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, env=env, cwd=tmp_path,
                          timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    import json

    got = json.loads(proc.stdout.strip().splitlines()[-1])
    for key in ("pkg", "lib", "mjcf"):
        assert got[key] and got[key].startswith(str(dest)), (key, got[key])  # not the checkout's
    assert got["entry"] == ["envisat_pose.datagen.plugin:load"] and got["cli"] == "envisat_pose.app.cli:main"
    assert got["scenarios"] == named_scenarios.names()
    assert got["git"] == "0123abc"  # no .git in a laid-out copy: the commit gpu_carry.sh recorded


def plan(leg, rounds=2):
    gt = script("gpu_train")
    return gt, [c for r in range(rounds) for c in gt.round_chunks(leg, r, named_scenarios.names())]


@pytest.mark.parametrize("leg", [1, 7])
def test_a_legs_chunks_are_valid_generate_configs_with_the_asked_mix(leg, tmp_path):
    gt, chunks = plan(leg)
    configs = []
    for i, c in enumerate(chunks):
        path = tmp_path / f"c{i}.toml"
        path.write_text(gt.to_toml(c["config"]))
        configs.append(resolve_job_config(GenerateConfig, {}, str(path),
                                          {"num_images": c["images"], "resolution_px": c["resolution"]}))
    random = [g for g in configs if g.mode == "random"]
    assert all(g.earth_probability >= 1 / 3 for g in random)  # the Earth behind the target in a third or more
    assert {g.resolution_px for g in random} >= {512, 1024, 2048}
    assert min(g.resolution_px for g in configs) == 512 and max(g.resolution_px for g in configs) == 2048
    seq = {g.sequence.scenario for g in configs if g.mode == "sequence"}
    assert seq == set(named_scenarios.names())  # every named scenario
    # the space camera at every severity: uncorrupted, benign, default and harsh ranges, and the paper's kinds
    read_noise = {g.corruption.sensor.read_noise_e for g in random if g.corruption.model == "sensor"}
    assert len(read_noise) >= 3 and any(g.corruption.model == "paper" for g in random)
    assert any(g.corruption.exposure == "none" and g.corruption.model == "sensor" for g in random)
    # the looks of a leg are its own
    assert len({g.appearance.texture_seed for g in configs}) == 1
    assert configs[0].appearance.texture_seed == gt.LOOK_SEED_BASE + 10 * leg
    assert any(g.appearance.specular != GenerateConfig().appearance.specular for g in random)


def test_an_online_leg_trains_on_the_offline_rounds_mix(tmp_path):
    """The online leg's looks file: every chunk of a round a look, at its resolution and camera, weighted by its
    images; every scenario's sequences with appearance off and on; seeds inside the leg's block."""
    from envisat_pose.pipelines.detector.look_mix import look_shares, read_looks

    gt, chunks = plan(3, rounds=1)
    looks = read_looks(gt.online_looks(str(tmp_path), 3, named_scenarios.names()))
    by_name = {look.name: look for look in looks}
    for c in chunks:
        look = by_name[c["name"]]
        assert look.generate.resolution_px == c["resolution"]
        if "scenario" in c:
            assert look.generate.mode == "sequence" and look.generate.sequence.scenario == c["scenario"]
            assert not look.generate.appearance_on and by_name[c["name"] + "-appearance"].generate.appearance_on
            assert look.generate.num_images == c["images"]
        else:
            assert look.weight == c["images"] and look.generate.earth_probability == c["config"]["earth_probability"]
    assert len(looks) == len(chunks) + len(named_scenarios.names())
    shares = dict(zip(by_name, look_shares(looks)))
    assert shares["random-1024-default"] == max(shares.values())
    seq_share = sum(n for name, n in shares.items() if name.startswith("sequence-"))
    offline = sum(c["images"] for c in chunks if "scenario" in c) / sum(c["images"] for c in chunks)
    assert abs(seq_share / 100 - offline) < 0.05
    seeds = [look.generate.seed for look in looks]
    assert len(set(seeds)) == len(seeds) and all(gt.SEED_BASE + 3 * gt.SEED_LEG <= s < gt.SEED_BASE + 4 * gt.SEED_LEG
                                                 for s in seeds)


def test_legs_never_share_a_data_seed():
    gt = script("gpu_train")
    chunks_per_round = len(gt.round_chunks(1, 0, named_scenarios.names()))
    assert chunks_per_round * 20 < gt.SEED_LEG  # 20 rounds of a leg stay inside its block of seeds


def test_a_round_is_sized_to_its_time_and_shares_the_cores_by_load():
    gt, chunks = plan(1, rounds=1)
    sized = gt.sized_round(chunks, seconds=100.0, rate=50.0, cores=16)
    load = sum(gt.load_of(c) for c in sized)
    assert abs(load - (100.0 - gt.START_S) * 50.0) < 0.02 * load  # the load the time allows at that rate
    assert [c["name"] for c in sized] == [c["name"] for c in chunks]
    for before, after in zip(chunks, sized):  # the proportions kept
        assert abs(after["images"] / before["images"] - sized[0]["images"] / chunks[0]["images"]) < 0.05
    assert all(c["workers"] >= 1 for c in sized)
    assert 16 <= sum(c["workers"] for c in sized) <= 16 + len(sized)  # every core, rounding aside
    big = max(sized, key=gt.load_of)
    assert big["workers"] == max(c["workers"] for c in sized)
    default = next(c for c in sized if c["name"] == "random-1024-default")
    assert gt.load_of(default) >= 0.3 * load  # the held-out sets' look keeps the largest share


def leaves(d: dict, prefix: str = "") -> dict:
    """A nested config as {"a.b.c": value} (lists as tuples)."""
    out = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(leaves(v, f"{prefix}{k}."))
        else:
            out[prefix + k] = tuple(v) if isinstance(v, list) else v
    return out


def inside(value, bounds) -> bool:
    return bounds[0] - 1e-9 <= value <= bounds[1] + 1e-9


def test_the_widest_looks_and_a_sequence_chunk_render(tmp_path):
    """One image of the widest random chunk and two frames of a sequence chunk through `envisat generate` (64 px):
    configs that validate can still fail in MuJoCo (32 texture sets passed 1000 materials). What the dry run
    writes is the chunk's: every key of its config in the data set's recorded config, the images 64 px with the
    MJCF camera's intrinsics at that size (f = 1024-px f x 64/1024), the wide look's draws inside its ranges, the
    leg's camera seed, and the sequence's frames frame_dt_s apart on the default scenario's 50 m hold."""
    from envisat_pose.app.cli import main
    from envisat_pose.datagen.dataset import iter_samples, sample_image
    from envisat_pose.geometry import load_camera
    from envisat_pose.shard_reader import load_dataset_manifest

    gt, chunks = plan(1, rounds=1)
    f_64 = load_camera().f_px * 64 / 1024
    out = {}
    for name in ("random-512-wide", "sequence-default"):
        chunk = next(c for c in chunks if c["name"] == name)
        toml = tmp_path / f"{name}.toml"
        toml.write_text(gt.to_toml(chunk["config"]))
        n = 2 if "sequence" in name else 1
        rc = main(["generate", "--config", str(toml), "--num-images", str(n), "--resolution", "64", "--seed", "3",
                   "--out", str(tmp_path / name), "--quiet"])
        assert rc == 0
        manifest = load_dataset_manifest(str(tmp_path / name))
        recorded = leaves(manifest["config"])
        asked = leaves(chunk["config"])
        assert {k: recorded.get(k) for k in asked} == asked  # the chunk's settings reached the data set
        samples = [(label, sample_image(members, label)) for _, label, members in iter_samples(str(tmp_path / name))]
        assert len(samples) == n
        for label, image in samples:
            # a lit frame shows the target; one in the Earth's shadow (the sequence's sun is drawn) is dark
            assert image.shape == (64, 64) and (image.std() > 1.0) != label["scene"]["eclipse"], image.std()
            np.testing.assert_allclose(np.array(label["K"]), [[f_64, 0, 31.5], [0, f_64, 31.5], [0, 0, 1]], rtol=1e-9)
            assert label["corruption"]["camera_seed"] == gt.LOOK_SEED_BASE + 10 + 3  # leg 1's camera
        out[name] = (chunk["config"], [label for label, _ in samples])

    wide, (label,) = out["random-512-wide"]
    scene = label["scene"]
    assert scene["mode"] == "random" and scene["appearance"] and scene["appendages"]
    for part in scene["look"]["materials"].values():
        for key in ("specular", "shininess", "reflectance"):
            assert inside(part[key], wide["appearance"][key]), (key, part[key])
    assert inside(scene["look"]["sun_intensity"], wide["lighting"]["sun_intensity"])
    assert inside(scene["earthshine"]["albedo"], wide["lighting"]["earth_albedo"])

    seq, labels = out["sequence-default"]
    assert [lab["scene"]["mode"] for lab in labels] == ["sequence"] * 2
    assert not any(lab["scene"]["appearance"] for lab in labels)  # round 0: appearance off
    t = [lab["scene"]["t_s"] for lab in labels]
    assert t[1] - t[0] == pytest.approx(seq["sequence"]["frame_dt_s"]) == pytest.approx(2.0)
    for lab in labels:  # the default scenario: a 50 m V-bar hold
        np.testing.assert_allclose(lab["x"][:3], [0.0, 50.0, 0.0], atol=1e-3)
        assert np.linalg.norm(lab["t_cam_from_target_m"]) == pytest.approx(50.0, abs=1e-3)
    # the target tumbles between the frames (its attitude changed) while the hold keeps it in place
    assert not np.allclose(labels[0]["x"][6:9], labels[1]["x"][6:9], atol=1e-3)


def test_a_fresh_target_leg_starts_from_the_backbone_it_is_given():
    """gpu_train.sh's BACKBONE (default 'shipped') reaches `envisat train --backbone` only for a fresh --target leg;
    a carried init wins."""
    from envisat_pose.app.cli import build_parser

    gt = script("gpu_train")
    assert gt.start_args("w.safetensors", None) == ["--init", "w.safetensors"]
    assert gt.start_args(None, "shipped") == ["--backbone", "shipped"]
    assert gt.start_args(None, None) == []
    assert gt.start_args(None, "none") == ["--backbone", "none"]  # from scratch: envisat train defaults to shipped
    ns = build_parser().parse_args(["train", "--target", "models/upper_stage.xml", "--out", "run",
                                    *gt.start_args(None, "shipped")])
    assert ns.backbone == "shipped" and ns.init is None


def test_gpu_carry_refuses_a_leg_that_is_not_a_number_or_has_no_weights(tmp_path):
    """`gpu_carry.sh --leg N` writes the leg the init weights ended; a leg that is not a count, or one without
    weights to start from, is refused in one line before anything is downloaded or written."""
    carry = tmp_path / "carry"
    for args, words in ((["--target-init", "w.safetensors", "--leg", "seven"], "expected the leg number"),
                        (["--leg", "7"], "without --init or --target-init")):
        proc = subprocess.run(["bash", os.path.join(ROOT, "scripts", "gpu_carry.sh"), *args, "--carry", str(carry)],
                              capture_output=True, text=True, timeout=60)
        assert proc.returncode == 2 and words in proc.stderr and len(proc.stderr.strip().splitlines()) == 1
        assert not carry.exists()
