"""Shared fixtures: MuJoCo truth trajectories from the lead's simulator (datagen), never the filter's model; and
the slow lane: the tests listed in SLOW are marked `slow` (pyproject.toml), so `make test` (-m "not slow") runs
in minutes and `make test-slow` / `make test-all` (CI) run them too."""

import pytest

from envisat_pose.datagen.gl_check import load_triton_before_mesa

# before any test module imports mujoco under MUJOCO_GL=osmesa (pytest imports them all when it collects): with
# the CUDA build of torch, triton loaded after Mesa's LLVM segfaults the first optimizer (gl_check.py)
load_triton_before_mesa()

# The slow end-to-end tests, by node id (a parametrized test without its [...] marks every case). Chosen from one
# `pytest --durations=60` run of the whole suite on the shared 2-core machine (2026-11-26, heavily loaded: 2650 s
# in all, ~4.4x the 10 minutes of a quiet machine): these took 1770 s of it (call time, plus the module fixtures
# only they use), leaving ~880 s, ~3.5 min on a quiet machine, to `make test`. Each module keeps at least one test
# in the fast lane. `make test` runs that lane in two processes (pytest-xdist, --dist loadfile: 6:05 in one, 3:37 in
# two on a quiet 2-core machine, 2026-11-27). Besides these, tests mark themselves @pytest.mark.slow in their
# files (`grep -rn mark.slow tests`: cold starts from unlabelled frames, the web viewer's screenshot, training runs,
# jobs with workers stopped by a signal).
# tests/test_architecture.py checks that every id names a test that exists.
SLOW = (
    "tests/pipelines/runs/test_memory.py::test_a_long_closed_loop_keeps_its_memory_flat",  # 401 s
    "tests/datagen/test_clearance.py::test_random_views_keep_the_camera_clear_and_the_target_beyond_the_near_plane",  # 336 s
    "tests/datagen/test_clearance.py::test_close_25m_keeps_clear_for_many_seeds",  # 58 s
    "tests/app/test_run.py::test_the_cli_runs_several_loops_in_parallel",  # 171 s
    # the shipped weights' floors: their module fixture (a fresh held-out set, scored) took 62 s
    "tests/perception/test_shipped_weights.py::test_localization_and_naming",
    "tests/perception/test_shipped_weights.py::test_visibility",
    "tests/perception/test_shipped_weights.py::test_calibrated_covariance",
    "tests/datagen/test_factory_shards.py::test_kill_then_resume_gives_the_uninterrupted_bytes",  # 51 s
    "tests/datagen/test_factory_shards.py::test_dask_two_workers_same_bytes",  # 45 s
    "tests/datagen/test_factory_shards.py::test_process_pool_two_workers_same_bytes",  # 40 s
    "tests/datagen/test_factory_shards.py::test_existing_dask_scheduler_by_address",  # 27 s
    "tests/filtering/test_consistency.py::test_camera_measurements_with_per_corner_detector_covariance[pixels]",  # 49 s
    "tests/filtering/test_reference_agreement.py::test_filterpy_and_batched_agree_over_100_steps[pixels]",  # 32 s
    # the tracker on frames: with the cold-start test (marked in its file) these use the module's generated
    # sequences (41 s to make)
    "tests/app/test_track.py::test_a_generate_folder_is_tracked_and_scored",  # 43 s
    "tests/app/test_track.py::test_timestamps_and_a_video",  # 27 s
    "tests/app/test_track.py::test_a_512_px_sequence_with_its_own_camera",  # 25 s
    "tests/app/test_montecarlo.py::test_same_seed_same_bytes_across_workers_and_dask",  # 42 s
    "tests/datagen/test_factory_overlap.py::test_prefetched_texture_equals_first_use",  # 28 s
    "tests/perception/test_facecue.py::test_calibrate_face_cue_reaches_the_detector",  # 28 s
    "tests/datagen/test_appearance.py::test_same_seed_same_bytes_with_appearance_and_clutter",  # 27 s
    "tests/app/test_estimate_cli.py::test_scenario_run_writes_the_contract_and_is_deterministic",  # 22 s
    "tests/app/test_scenarios.py::test_rate_sweep_writes_one_campaign_per_rate_its_figure_and_report",  # 21 s
    # added after that run: a fresh process compiling a kernel (~30 s loaded); its other case stays fast
    "tests/filtering/test_fast_kernel.py::test_the_compiled_cache_goes_to_the_user_cache_folder[True]",
    # the fast lane took 6:12 on a clean checkout (2026-11-26, with another job for its first 90 s): the slowest of
    # it moved here (call times from a loaded --durations run)
    "tests/test_wheel_install.py::test_wheel_installs_and_simulates_from_another_folder",  # 21 s: a wheel, a venv
    "tests/perception/test_train.py::test_overfit_drives_the_loss_down",  # 15 s
    "tests/perception/test_stream.py::test_time_budget_stops_inside_it_with_a_checkpoint_and_a_decayed_rate",  # 14 s
    "tests/perception/test_ddp.py::test_two_ranks_hold_identical_weights",  # 13 s: two processes under gloo
    "tests/filtering/test_consistency.py::test_camera_measurements_with_per_corner_detector_covariance[pixels+range]",
    "tests/app/test_estimate_cli.py::test_truth_file_and_rate",  # 10 s
    "tests/app/test_track_inputs.py::test_an_interrupt_leaves_the_earlier_outputs_and_a_finished_run_removes_stale_ones",
    # a trainer and its worker interrupted by a process-group SIGINT, then resumed under a 20 s budget
    "tests/perception/test_train_path.py::test_ctrl_c_writes_a_checkpoint_and_resume_honours_a_new_budget",  # 26 s
    # three online runs, each starting a renderer process
    "tests/pipelines/detector/test_online_train.py::test_an_online_run_resumes_to_the_weights_of_an_uninterrupted_one",  # 15 s
    # two renderers at 2048 px for the marker plates of another target (issue 48)
    "tests/datagen/test_targets.py::test_labels_land_on_the_rendered_site_markers",  # 17 s
    # the fast lane took 5:43 on a quiet clean checkout (2026-11-28, 792 tests; the floor is 5 minutes): its
    # slowest moved here (call times of a --durations run, partly loaded), each file keeping fast tests
    "tests/pipelines/tracking/test_tracker.py::test_a_measured_apparent_scale_is_undone_and_its_spread_reported",  # 18 s
    "tests/pipelines/tracking/test_tracker.py::test_the_correlation_falls_with_the_views_rotation_at_the_tracked_rate",  # 14 s
    "tests/pipelines/tracking/test_tracker.py::test_correlated_detector_errors_are_allowed_for_by_the_filters_memory",  # 12 s
    "tests/pipelines/tracking/test_tracker.py::test_a_confidently_wrong_appearance_cannot_decide_the_half_turn_alone",  # 11 s
    "tests/pipelines/tracking/test_tracker.py::test_errors_the_error_model_misses_are_allowed_for_by_the_detector_process_noise",
    "tests/pipelines/tracking/test_tracker.py::test_an_array_seen_at_the_other_end_loses_a_decided_track",  # 9 s
    "tests/pipelines/tracking/test_tracker.py::test_the_range_error_no_frame_averages_away_stays_in_the_covariance",  # 9 s
    "tests/pipelines/adaptation/test_pseudo_labels.py::test_smoothing_a_tumbling_truth_beats_the_filter",  # 10 s
    "tests/pipelines/detector/test_online.py::test_batches_repeat_and_a_stopped_run_resumes_after_what_it_trained",  # 9 s
    "tests/pipelines/test_jobs.py::test_montecarlo_verb_and_library_agree",  # 8 s
    "tests/perception/test_train_path.py::test_a_plain_script_without_a_main_guard_trains_with_workers",  # 8 s
    "tests/perception/test_naming.py::test_line_cues_help_with_many_spurious_junctions",  # 8 s
    # with those moved the lane took 5:01 (780 tests, warm): seven more
    "tests/pipelines/tracking/test_tracker.py::test_a_lost_track_is_detected_and_recovered",  # 6 s
    "tests/pipelines/tracking/test_tracker.py::test_a_burst_beyond_the_detectors_own_covariance_is_gated_with_gate_raw",  # 6 s
    "tests/pipelines/adaptation/test_pseudo_labels.py::test_the_smoother_does_not_reach_across_a_lost_frame",  # 7 s
    "tests/datagen/test_truth_physics.py::test_clohessy_wiltshire_limit_of_a_circular_chief",  # 7 s
    "tests/pipelines/adaptation/test_edge_range.py::test_unmeasurable_frames_give_no_delta",  # 7 s
    "tests/perception/test_schedule.py::test_a_budget_that_ends_before_the_cooldown_still_leaves_the_next_legs_start",
    "tests/pipelines/test_jobs.py::test_the_plain_constructor_and_resolve_job_give_the_same_estimates",  # 6 s
    # a clean checkout's lane took 5:08 and a warm one 5:13 (775 tests, 2026-11-29): three more (4:18 after)
    "tests/pipelines/tracking/test_tracker.py::test_the_tracker_starts_cold_and_converges",  # 24 s
    "tests/app/test_out_folders.py::test_montecarlo_makes_its_parents",  # 16 s
    "tests/app/test_adapt.py::test_the_apparent_scale_is_measured_against_the_labels",  # 13 s with its fixture
    # a quiet clean checkout's lane took 5:44 (1679 tests, 2026-12-07): the slowest ends to ends moved here (call
    # times of that run's --durations), each file keeping fast tests
    "tests/datagen/test_shard_no_room.py::test_generate_on_a_full_disk_is_one_line_and_leaves_no_partial_shard",  # 17 s
    "tests/pipelines/test_jobs.py::test_estimate_verb_and_library_agree",  # 15 s
    "tests/app/test_view.py::test_web_viewer_serves_on_loopback_only_and_is_torn_down",  # 12 s
    "tests/app/test_track.py::test_the_512_px_track_claims_the_truths_attitude",  # 12 s: the last fast user of track_512
    "tests/app/test_montecarlo.py::test_a_sweep_is_refused_where_it_does_not_belong",  # 10 s
    "tests/perception/test_detect_cli.py::test_a_damaged_roi_file_is_one_error_and_leaves_no_file_open",  # 9 s
    "tests/pipelines/campaigns/test_pcrlb_failures.py::test_half_the_keypoints_failing_bounds_like_twice_the_noise_variance",
    "tests/app/test_montecarlo_target.py::test_a_target_file_named_from_elsewhere_is_the_same_file",  # 8 s
    "tests/pipelines/detector/test_online.py::test_each_ddp_rank_renders_its_own_frames_under_one_state",  # 7 s
    "tests/app/test_track.py::test_a_sequence_in_the_earths_shadow_has_no_lit_frame",  # 6 s
    "tests/perception/test_detect_bf16.py::test_bfloat16_finds_the_float32_corners",  # 6 s
    # with those moved the lane took 5:14 (1668 tests, quiet, clean): six more (seven cases)
    "tests/pipelines/tracking/test_tracker.py::test_a_covariance_too_wide_for_the_claim_never_says_tracking",  # 5-14 s
    "tests/app/test_sigterm.py::test_ctrl_c_to_a_generate_with_workers_leaves_no_partial_shard",  # 7 s
    "tests/pipelines/campaigns/test_unfixed_start.py::test_estimate_and_montecarlo_warn_on_a_rod_seen_along_its_axis",
    "tests/datagen/test_scenario_sense.py::test_the_body_rate_bound_is_what_eulers_equations_reach",  # 10 s, 2 cases
    "tests/app/test_run_target.py::test_the_closed_loop_of_another_target_writes_its_keypoints",  # 6 s
    "tests/app/test_estimate_cli.py::test_truth_file_of_another_target_is_estimated_with_its_keypoints",  # 6 s
    # then 4:58 (1660 tests): two written-config reruns of whole loops and tracks (estimate's and montecarlo's stay)
    "tests/app/test_run_target.py::test_the_written_config_records_the_target_files_sha256_and_a_rerun_refuses_the_file_changed",
    "tests/app/test_track_target.py::test_the_written_config_records_the_target_files_sha256_and_a_rerun_refuses_the_file_changed",
    # the lane took 6:09 on a slower day (1750 tests, quiet, 2026-12-07, sixth session): the slowest calls of that
    # run's --durations moved here (a parametrized test keeps its other cases fast)
    "tests/app/test_sweep_config.py::test_the_written_config_reruns_the_same_sweep",  # 9 s
    "tests/app/test_montecarlo.py::test_the_written_config_records_the_target_files_sha256_and_a_rerun_refuses_the_file_changed",
    "tests/app/test_report.py::test_report_names_each_campaigns_target",  # 9 s
    "tests/app/test_estimate_cli.py::test_simulate_records_the_target_files_sha256_and_an_edit_since_is_refused",  # 6 s
    "tests/envisat_pose/test_target.py::test_the_fast_visibility_table_calls_hidden_only_what_is_hidden[span0-upper_stage]",
    "tests/app/test_montecarlo.py::test_a_campaign_stopped_while_its_figures_are_written_is_not_taken_as_finished",
    "tests/app/test_track_inputs.py::test_library_messages_stay_off_the_terminal",  # 6 s
    "tests/filtering/test_visibility_check.py::test_three_markers_on_a_target_that_does_not_tumble_stay_consistent",
    "tests/app/test_montecarlo_target.py::test_naming_envisats_file_changes_nothing_and_a_bad_file_is_refused",  # 6 s
    "tests/app/test_estimate_cli.py::test_a_corrupt_truth_file_is_one_error_line[text]",  # 5 s
    "tests/app/test_estimate_cli.py::test_a_corrupt_truth_file_is_one_error_line[config_without_orbit]",  # 5 s
    "tests/app/test_gl_platform.py::test_a_blank_value_renders_as_unset",  # 5 s
    "tests/app/test_run.py::test_a_run_that_never_tracks_says_so",  # 5 s
    "tests/perception/test_ddp.py::test_the_process_group_ends_with_no_training_object_holding_it",  # 5 s
    "tests/app/test_shipped_weights_named.py::test_run_and_track_name_the_shipped_weights_and_their_written_configs_take_the_name_back",
    "tests/scripts/test_gpu_recipe.py::test_an_online_leg_trains_on_the_offline_rounds_mix",  # 4 s
    "tests/filtering/test_reference_agreement.py::test_filterpy_and_batched_agree_over_100_steps[markers3d]",  # 4 s
    "tests/app/test_montecarlo_target.py::test_estimate_on_a_target_the_test_builds_is_consistent_and_at_its_bound",
    "tests/pipelines/detector/test_online.py::test_frames_are_the_factory_samples",  # 4 s
    "tests/bench/test_scripts.py::test_target_trackings_stand_in_tracks_on_frames_of_the_cameras_size",  # 4 s
    "tests/datagen/test_independent_eccentric_orbit.py::test_filter_rk4_model_against_the_independent_reference[circular]",
    "tests/app/test_montecarlo_target.py::test_an_upper_stage_campaign_is_bounded_by_its_own_pcrlb",  # 4 s
    # with those moved and the verbs' start 0.7 s shorter (no scipy.stats) the lane took 5:01 (1731 tests): more
    "tests/filtering/test_filter_step.py::test_a_released_run_starts_again_from_a_covariance_that_fits_its_error",
    "tests/envisat_pose/test_target.py::test_the_fast_visibility_table_calls_hidden_only_what_is_hidden[span1-upper_stage]",
    "tests/envisat_pose/test_target.py::test_the_fast_visibility_table_calls_hidden_only_what_is_hidden[span0-cubesat_3u]",
    "tests/perception/test_naming.py::test_naming_recovers_names_or_flags_the_half_turn",  # 5 s
    "tests/datagen/test_clearance.py::test_a_15m_hold_through_the_array_is_refused",  # 5 s
    "tests/filtering/test_sigma_chart.py::test_rod_on_its_tips_keeps_the_rotation_about_its_axis_unknown",  # 4 s
    "tests/pipelines/tracking/test_tracker_target.py::test_twins_nothing_tells_apart_are_one_pose_whatever_the_detector_names",
    "tests/pipelines/tracking/test_tracker_api.py::test_the_target_is_taken_as_a_target_or_its_file_by_both_constructors",
    "tests/analysis/test_campaign_figures.py::test_block_norms_nees_nis_and_rmse_vs_bound_figures",  # 4 s
    "tests/filtering/test_visibility_check.py::test_the_fused_kernel_and_the_numpy_filter_drop_the_same_keypoints_under_the_spread[models/upper_stage.xml]",
    "tests/app/test_montecarlo.py::test_killed_campaign_resumes_to_the_same_bytes",  # 4 s
    "tests/app/test_montecarlo.py::test_the_public_pipeline_writes_what_the_verb_writes",  # 4 s
    "tests/app/test_montecarlo.py::test_a_folder_of_another_jobs_files_is_refused",  # 3 s
    "tests/app/test_written_source.py::test_a_written_config_names_the_version_and_commit_that_made_it[sweep]",  # 3 s
    "tests/scripts/test_gpu_recipe.py::test_the_widest_looks_and_a_sequence_chunk_render",  # 3 s
    "tests/pipelines/detector/test_online_train.py::test_a_resumed_online_run_refuses_shards_and_another_k",  # 3 s
    "tests/app/test_run.py::test_a_run_at_another_size_says_which_pixels_are_whose",  # 3 s
    "tests/datagen/test_factory_overlap.py::test_overlap_and_prefetch_same_bytes[kw0]",  # 3 s
    "tests/filtering/test_torque_free_closed_forms.py::test_filter_rk4_model_converges_to_the_closed_forms[major]",
    "tests/datagen/test_independent_eccentric_orbit.py::test_filter_rk4_model_against_the_independent_reference[e0.1]",
    # a clean clone's lane took 5:03 with the bounds' tests (1815 tests, 2026-12-07, sixth session): 28 more
    "tests/app/test_simulate_cli.py::test_bad_config_gets_a_clear_message_and_writes_nothing[[relative]\nrho0_C_m = [0.0, 15.0, 0.0]\n-relative.rho0_C_m-m from geom 'array']",
    "tests/pipelines/tracking/test_tracker_target.py::test_one_keypoint_named_as_its_twin_does_not_decide_the_twins",
    "tests/app/test_run.py::test_a_short_closed_loop_writes_every_output",  # 3 s
    "tests/app/test_estimate_cli.py::test_a_corrupt_truth_file_is_one_error_line[empty]",  # 3 s
    "tests/app/test_estimate_cli.py::test_a_corrupt_truth_file_is_one_error_line[truncated]",  # 3 s
    "tests/app/test_estimate_cli.py::test_a_corrupt_truth_file_is_one_error_line[random_bytes]",  # 3 s
    "tests/filtering/test_torque_free_closed_forms.py::test_filter_rk4_model_converges_to_the_closed_forms[long]",
    "tests/filtering/test_torque_free_closed_forms.py::test_filter_rk4_model_converges_to_the_closed_forms[upper_stage]",
    "tests/app/test_montecarlo.py::test_a_campaign_that_never_measures_says_so",  # 3 s
    "tests/pipelines/tracking/test_tracker.py::test_the_tracker_claims_no_pose_through_a_camera_its_frames_contradict",
    "tests/datagen/test_views_sized.py::test_a_sequence_showing_the_target_as_a_dot_is_refused",  # 3 s
    "tests/datagen/test_views_sized.py::test_a_cubesat_covers_about_envisats_share_of_the_image",  # 3 s
    "tests/app/test_montecarlo.py::test_a_campaign_written_before_a_config_field_existed_resumes",  # 3 s
    "tests/datagen/test_independent_eccentric_orbit.py::test_filter_rk4_model_against_the_independent_reference[molniya]",
    "tests/pipelines/adaptation/test_edge_response.py::test_the_edge_in_linear_light_sits_on_the_true_step[linear]",
    "tests/perception/test_trainer_hooks.py::test_pre_cooldown_weights_are_kept_once_and_at_a_budgets_stop_only",
    "tests/app/test_rrd_cli.py::test_montecarlo_rrd",  # 3 s
    "tests/pipelines/test_library_args.py::test_a_campaign_runs_on_one_process_by_default_and_refuses_a_runner_of_another_type",
    "tests/app/test_report.py::test_report_names_the_target_a_scenario_file_gives",  # 3 s
    "tests/pipelines/test_verb_parity.py::test_run_campaign_refuses_a_rate_sweep_and_run_sweep_runs_it",  # 2 s
    "tests/filtering/test_step_update.py::test_markers_far_finer_than_the_prior_give_a_consistent_campaign",  # 2 s
    "tests/perception/test_naming.py::test_views_with_missed_corners_are_named",  # 2 s
    "tests/pipelines/test_concurrent_outputs.py::test_a_rerun_without_the_plot_removes_the_earlier_runs_plot",  # 2 s
    "tests/analysis/test_plots.py::test_plots_are_written_and_show_the_data",  # 2 s
    "tests/app/test_written_source.py::test_a_written_config_names_the_version_and_commit_that_made_it[montecarlo]",
    "tests/app/test_estimate_cli.py::test_runs_whose_every_update_fails_are_not_said_to_miss_the_target",  # 2 s
    "tests/datagen/test_appearance.py::test_appearance_changes_pixels_not_labels_masks_or_depth",  # 2 s
    "tests/pipelines/test_concurrent_outputs.py::test_an_interrupted_simulate_and_estimate_leave_the_earlier_runs_files_as_a_set",
)


def _slow(nodeid: str) -> bool:
    return nodeid in SLOW or nodeid.split("[", 1)[0] in SLOW


def pytest_collection_modifyitems(config, items):
    for item in items:
        if _slow(item.nodeid):
            item.add_marker(pytest.mark.slow)


@pytest.fixture(scope="session")
def truth_600():
    """The default scenario (50 m V-bar hold, 134.74 s tumble), 600 s at 1 s, simulated by MuJoCo."""
    from envisat_pose.datagen.scenario import scenario_config
    from envisat_pose.datagen.truth import simulate_truth

    return simulate_truth(scenario_config("default", duration_s=600.0, seed=0))


@pytest.fixture(scope="session")
def truth_1800():
    """The default scenario over its full 1800 s (MuJoCo), another random initial attitude."""
    from envisat_pose.datagen.scenario import scenario_config
    from envisat_pose.datagen.truth import simulate_truth

    return simulate_truth(scenario_config("default", duration_s=1800.0, seed=1))


@pytest.fixture(scope="session")
def chaser_of():
    """A function: truth trajectory -> (T, 4) chaser polar state."""
    from envisat_pose.filtering.estimator import chaser_states

    return lambda tr: chaser_states(tr.chaser_r_m, tr.chaser_rdot_m_s, tr.chaser_theta_rad, tr.chaser_thetadot_rad_s)


@pytest.fixture
def machine(monkeypatch, tmp_path):
    """Pretend a machine's size: machine(cores, affinity=None, quota=None, memory_gb=None) sets os.cpu_count to
    cores, the CPU affinity to its first `affinity` cores (default all), a cgroup v2 CPU quota of `quota` cores
    (default none) and MemAvailable to memory_gb (default 1000), all that envisat_pose.pools.usable_cores and
    usable_memory_bytes read."""
    import os

    from envisat_pose import pools

    def pretend(cores: int, affinity: int | None = None, quota: int | None = None, memory_gb: float = 1000.0):
        root = tmp_path / "machine"
        root.mkdir(exist_ok=True)
        (root / "cpu.max").write_text(f"{quota * 100000} 100000\n" if quota else "max 100000\n")
        (root / "meminfo").write_text(f"MemTotal: 1 kB\nMemAvailable: {int(memory_gb * 1e9 / 1024)} kB\n")
        monkeypatch.setattr(os, "cpu_count", lambda: cores)
        monkeypatch.setattr(os, "sched_getaffinity", lambda pid: set(range(affinity or cores)))
        monkeypatch.setattr(pools, "CGROUP_ROOT", str(root))
        monkeypatch.setattr(pools, "MEMINFO", str(root / "meminfo"))

    return pretend


@pytest.fixture(autouse=True)
def _from_a_folder_of_its_own(tmp_path_factory, monkeypatch):
    """Every test runs from an empty folder of its own, not the checkout: a test that names a repository file by
    the working folder fails here, as it would for a user who runs pytest from elsewhere, and nothing a test
    writes by a relative path lands in the checkout (read-only for some users). A test's module fixtures are
    built before it, where pytest started."""
    monkeypatch.chdir(tmp_path_factory.mktemp("cwd"))
