"""Loading the fused filter's code before the first frame (filtering/kernel_warmup.py): the dummy step compiles or
loads exactly the overloads a real step of the same setup calls (a real step after it adds none), for ENVISAT's
box and for a target with a visibility table, and the background form runs only for the fused kernel (kernel 'fast'
in the additive chart)."""

import dataclasses

import numpy as np
import pytest

from envisat_pose.filtering import fast
from envisat_pose.filtering.estimator import FilterConfig, Measurement, filter_step, init_state, make_setup
from envisat_pose.filtering.kernel_warmup import load_in_background, load_kernels
from envisat_pose.target import load_target

ENTRY_KERNELS = ("predict_kernel", "update_kernel", "table_visible_kernel", "_chaser_stages")


def signatures() -> dict[str, list]:
    return {name: list(getattr(fast, name).signatures) for name in ENTRY_KERNELS}


def real_step(setup, R: int) -> None:
    """One filter step of R runs near a real view (the target 45-55 m along the camera's axis, measured where
    the model puts its keypoints, a few of them missing), as a tracker's bank makes it."""
    rng = np.random.default_rng(7)
    cfg = setup.cfg
    x = np.zeros((R, 12))
    x[:, :3] = setup.camera.pos_C_m + setup.camera.R_K_from_C.T @ [0.0, 0.0, 50.0] + rng.normal(0, 5, (R, 3))
    x[:, 6:9] = rng.normal(0, 0.2, (R, 3))
    x[:, 9:] = rng.normal(0, 0.01, (R, 3))
    chaser = np.array([7.1e6, 0.0, 0.0, 1.06e-3])
    state = init_state(x, cfg.P0, 0.0, chaser, cfg)
    z = setup.hx(x) + rng.normal(0, 0.5, (R, setup.num_keypoints, 2))
    mask = rng.random((R, setup.num_keypoints)) > 0.2
    filter_step(state, Measurement(1.0, chaser, z, mask, 0.25 * np.eye(2)), setup)


@pytest.mark.parametrize("target", [None, "models/upper_stage.xml"])
def test_the_warm_up_loads_the_overloads_a_real_step_calls(target):
    setup = make_setup(FilterConfig(), "pixels", target=None if target is None else load_target(target))
    load_kernels(setup)
    loaded = signatures()
    assert loaded["predict_kernel"] and loaded["update_kernel"]
    if target is not None:
        assert loaded["table_visible_kernel"]  # the target's table looked up before the update
    for R in (1, 3):
        real_step(setup, R)
    assert signatures() == loaded  # nothing compiled or loaded at the real steps


def test_the_background_load_runs_for_the_fused_kernel_only():
    setup = make_setup(FilterConfig(), "pixels")
    thread = load_in_background(setup)
    assert thread is not None and not thread.daemon  # joined at the interpreter's exit
    thread.join(timeout=600.0)  # a machine without numba's cache compiles here
    assert not thread.is_alive() and signatures()["update_kernel"]
    reference = make_setup(dataclasses.replace(FilterConfig(), kernel="reference"), "pixels")
    assert load_in_background(reference) is None
    # the rotation chart runs the numpy filter (the fused kernels are the additive chart's): nothing to load
    rotation = make_setup(dataclasses.replace(FilterConfig(), sigma_chart="rotation"), "pixels")
    assert load_in_background(rotation) is None
