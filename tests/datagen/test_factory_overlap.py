"""The factory's hot path (issue 18): finishing sample k beside the render of sample k + 1, and making the Earth
textures on a helper thread, leave every byte as finishing one sample after the other and making textures at
first use; an error while finishing a sample publishes no shard."""

import os

os.environ.setdefault("MUJOCO_GL", "osmesa")

import numpy as np
import pytest

from envisat_pose.config import from_dict
from envisat_pose.datagen import factory
from envisat_pose.datagen.factory import run_generate
from envisat_pose.datagen.generate_config import GenerateConfig


def cfg_of(**kw):
    base = {"num_images": 8, "shard_size": 4, "resolution_px": 96, "seed": 11, "earth_probability": 0.5}
    base.update(kw)
    return from_dict(GenerateConfig, base)


def shas(manifest):
    return [(e["name"], e["sha256"], e["count"]) for e in manifest["shards"]]


@pytest.mark.parametrize("kw", [{}, {"storage": "clean"}, {"mode": "sequence", "num_images": 6}])
def test_overlap_and_prefetch_same_bytes(tmp_path, monkeypatch, kw):
    cfg = cfg_of(**kw)
    monkeypatch.setattr(factory, "FINISH_BESIDE_RENDER", False)
    monkeypatch.setattr(factory, "PREFETCH_EARTH_MIN_IMAGES", 10**9)
    serial = run_generate(cfg, str(tmp_path / "serial"))
    monkeypatch.setattr(factory, "FINISH_BESIDE_RENDER", True)
    monkeypatch.setattr(factory, "PREFETCH_EARTH_MIN_IMAGES", 1)
    from envisat_pose.datagen import render_cache

    render_cache.close_renderers()  # a fresh renderer: its Earth textures come from the prefetch
    overlapped = run_generate(cfg, str(tmp_path / "overlapped"))
    assert shas(serial) == shas(overlapped)


def test_error_while_finishing_publishes_no_shard(tmp_path, monkeypatch):
    calls = {"n": 0}
    real = factory.finish_sample

    def failing(*args, **kw):
        calls["n"] += 1
        if calls["n"] == 3:
            raise RuntimeError("boom")
        return real(*args, **kw)

    monkeypatch.setattr(factory, "finish_sample", failing)
    out = tmp_path / "ds"
    with pytest.raises(RuntimeError, match="boom"):
        run_generate(cfg_of(), str(out))
    assert not any(p.name.endswith(".tar") for p in out.iterdir())


def test_prefetched_texture_equals_first_use():
    from envisat_pose.datagen.earth import earth_cap_texture
    from envisat_pose.datagen.render import SceneRenderer

    r = SceneRenderer(64, earth_seed=7)
    try:
        r.prefetch_earth_textures()
        r._upload_earth_texture("earth_cap", 1)
        m = r.model
        t = m.texture("earth_cap_tex_1").id
        a, w = int(m.tex_adr[t]), int(m.tex_width[t])
        want = earth_cap_texture(7, w, 1)
        assert np.array_equal(m.tex_data[a : a + want.size], want.ravel())
    finally:
        r.close()


def test_helpers_only_where_a_core_is_spare(monkeypatch, machine):
    machine(2)
    monkeypatch.setenv("LP_NUM_THREADS", "1")
    assert factory.spare_core(1) and not factory.spare_core(2)
    assert not factory.spare_core(1, "dask", "tcp://127.0.0.1:8786")
    monkeypatch.setenv("LP_NUM_THREADS", "2")
    assert not factory.spare_core(1)
    monkeypatch.delenv("LP_NUM_THREADS")
    assert not factory.spare_core(1)  # the run sets it to the worker's share


def test_the_rasterizer_threads_are_the_cores_shared_by_the_workers_that_start(monkeypatch, tmp_path, machine):
    """8 workers asked for a dataset of 2 shards on 8 cores: 2 processes start, 4 llvmpipe threads each (not 1);
    64 by os.cpu_count but 2 by affinity: 2, not 64. A resume counts the shards it has left, not the dataset's: one
    shard of 2 left for 2 workers on 2 cores starts one process, with both cores (it had 1, a core idle), and that
    process has a core spare beside LP_NUM_THREADS = 1 (the helper threads on)."""
    runners, besides, left = [], [], {}

    class Job:
        def __init__(self, out_dir):
            self.out_dir = out_dir
            self.header = {"target": {"sha256": "0" * 64}}  # what the written config records (a real job's header)

        def open(self):
            os.makedirs(self.out_dir, exist_ok=True)  # the output lock (out_lock) made it already

        def resume(self, opened):
            return {}

        def todo(self):
            return left.get(self.out_dir, [0, 1])  # a fresh run: every shard

        def run(self, task, args, runner, on_unit):
            runners.append(runner)
            besides.append(args(self.todo()[0])[3])
            return {}

    monkeypatch.setattr(factory, "dataset_job", lambda cfg, out_dir: Job(out_dir))
    monkeypatch.delenv("LP_NUM_THREADS", raising=False)
    cfg = GenerateConfig(num_images=8, shard_size=4, resolution_px=64)
    machine(8)
    factory.run_generate(cfg, str(tmp_path / "a"), workers=8)
    machine(64, affinity=2)
    factory.run_generate(cfg, str(tmp_path / "b"), workers=1)
    left[str(tmp_path / "c")] = [1]  # a resume with shard 1 left
    factory.run_generate(cfg, str(tmp_path / "c"), workers=2)
    assert [r.env for r in runners] == [{"LP_NUM_THREADS": "4"}, {"LP_NUM_THREADS": "2"}, {"LP_NUM_THREADS": "2"}]
    monkeypatch.setenv("LP_NUM_THREADS", "1")
    factory.run_generate(cfg, str(tmp_path / "c"), workers=2)
    assert besides[-1] is True


def test_gil_switch_interval_restored(tmp_path, monkeypatch):
    import sys

    before = sys.getswitchinterval()
    monkeypatch.setattr(factory, "FINISH_BESIDE_RENDER", True)
    run_generate(cfg_of(num_images=4, earth_probability=0.0), str(tmp_path / "ds"))
    assert sys.getswitchinterval() == before
