"""The suite's long form: the tests that the per-commit run leaves out, and why.

The README's test command (``python -m pytest -q``: the whole suite, no ``-m``) is the
per-commit run. It leaves out the tests named in ``LONG``, and CI runs them right after it
(``.ci/run``: ``python -m pytest -q -m long``), so every test still runs before anything
lands. ``-m long`` selects them alone; naming a file or a test on the command line runs it
whatever this says; ``SIMSERVER_SLOW=1`` runs everything, long forms included.

Why (issue 33 item 3, a suite a contributor runs before every commit, 5 minutes on this
2-core machine): the whole suite took 1110 s of wall time and 1087 s of CPU (recorded run
at 84e0b9f, 2026-12-07, warm kernel cache, load 0.6-2.1), so it is CPU-bound: two pytest
workers sharing its files (pytest-xdist ``-n 2 --dist loadfile``) took it only to 839 s in
the same session, and broke seven tests (live tests beside the other worker's servers, and
two bit-identity checks between a world of one and its single car: found later, a kernel
compiled with fused multiply-adds gets other last bits when another process compiled its
callees, see ``beside_kernel_cache``). The per-commit run's two workers therefore each take
one fixed half (``BESIDE``), each with its own kernel cache. The time goes to real
processes: a live server costs a quarter to 0.4 of a core while it runs
(its 1 kHz loop), and each server, client or command line a test starts pays Python's and
numba's start-up (about 1 s of CPU warm).

So a test is here when, in that recorded run, its setup + call + teardown took 2 s or
more (the figure beside its name: seconds of wall time then), because of what its file's
entry says it runs, or when it shares a module fixture with such a test whose setup took
that time (left in the per-commit run, it would pay that setup), unless it is in
``PER_COMMIT``: the tests kept in the per-commit run despite their cost, each because it
is the per-commit run's one end-to-end check of a path. The per-commit run keeps every
test under 2 s, the tire kernels' tests, the headless physics, the protocol, the configs
and the docs checks.

A name here that the suite does not have is an error when the whole suite is collected
(a test renamed or removed must be renamed or removed here too). ``python -m tests.long_form``
prints the list with the reasons, and the totals.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path
from typing import Any

LONG: dict[str, tuple[str, dict[str, float]]] = {
    "tests/test_cli.py": (
        "a run-scenario process writing its plots", {
            "test_run_scenario_writes_history_summary_and_plots": 3.3,
        }),
    "tests/test_client_defects.py": (
        "a live server and a driver client holding the car on a hill for seconds", {
            "test_joystick_driver_with_pedals_at_rest_holds_the_car_on_a_hill": 12.8,
            "test_keyboard_driver_holds_the_car_on_a_hill_until_the_throttle": 5.4,
            "test_recorder_metadata_per_segment_after_a_load_and_a_reset": 3.2,
        }),
    "tests/test_client_trust.py": (
        "a live server, a recorder and a forging process", {
            "test_the_recorder_drops_fake_states_and_keeps_only_the_real_segments": 3.8,
        }),
    "tests/test_clients.py": (
        "a live server and client processes (drivers, player, recorder) for seconds of real time", {
            "test_every_client_without_a_server_exits_3_quickly_with_a_clear_message": 3.1,
            "test_gamepad_auto_hold_on_a_10pct_hill[8s]": 20.5,
            "test_joystick_driver_on_sdls_virtual_joystick": 5.0,
            "test_keyboard_auto_hold_on_a_10pct_hill[8s]": 12.9,
            "test_keyboard_driver_in_a_pseudo_terminal": 5.2,
            "test_keyboard_driver_rearms_its_hold_and_names_the_new_car_after_a_load_by_another_client": 5.4,  # noqa: E501
            "test_keyboard_driver_shows_road_lane_s_and_edge_on_an_opendrive_road": 2.5,
            "test_player_and_recorder_reproduce_the_headless_e2_stop": 8.3,
            "test_recorder_row_groups_rrd_and_a_clean_sigterm": 4.0,
        }),
    "tests/test_collision_live.py": (
        "two cars driven into contact on a live server", {
            "test_a_car_driven_into_a_held_car_publishes_one_collision": 6.8,
        }),
    "tests/test_compare.py": (
        "simserver compare processes over recorded runs, with plots", {
            "test_a_time_shifted_copy_aligns_back_to_zero": 5.0,
            "test_bad_inputs_give_one_line_naming_the_file": 4.5,
            "test_one_segment_of_a_recording_like_file": 5.0,
            "test_readme_command_as_written": 3.6,
        }),
    "tests/test_connection_errors.py": (
        "TLS servers and viewers as processes", {
            "test_a_plain_tcp_view_of_a_tls_server_says_it_wants_tls": 4.3,
            "test_plain_tcp_to_a_tls_server_is_told_it_speaks_tls": 5.5,
            "test_view_with_each_documented_client_config_draws[credentials-driver]": 2.5,
            "test_view_with_each_documented_client_config_draws[credentials-viewer]": 2.8,
            "test_view_with_each_documented_client_config_draws[mutual-tls-viewer]": 4.9,
        }),
    "tests/test_dockerfile.py": (
        "the image's install steps in a fresh venv", {
            "test_image_install_steps_short_form": 6.4,
        }),
    "tests/test_driver.py": (
        "30 s of simulated driving on an OpenDRIVE lane", {
            "test_follows_a_lane_of_curves_elevation_at_15_mps_within_0p3_m_rms[30s]": 5.8,
        }),
    "tests/test_drop_publishers.py": (
        "CPU hogs beside a live server and its publishers", {
            "test_drop_publishers_under_cpu_load_keep_their_command_stream[project-config]": 13.0,
            "test_drop_publishers_under_cpu_load_keep_their_command_stream[zenoh-defaults-both]": 13.0,  # noqa: E501
            "test_drop_publishers_under_cpu_load_keep_their_command_stream[zenoh-defaults-client-mismatched]": 25.2,  # noqa: E501
        }),
    "tests/test_faults.py": (
        "a live server under faults (floods, soaks, kills, restarts) for seconds", {
            "test_client_killed_mid_drive_trips_the_watchdog_and_the_car_holds": 5.1,
            "test_command_flood_far_above_1khz": 8.6,
            "test_kill_9_loses_at_most_the_last_100_ms_of_the_command_log": 2.8,
            "test_router_restart_between_client_and_server": 5.2,
            "test_short_realtime_soak_loses_no_command": 22.0,
            "test_sigterm_mid_drive_exits_cleanly_with_a_complete_replayable_log": 5.7,
            "test_slow_and_frozen_subscribers_do_not_stop_the_server": 5.8,
            "test_vanishing_viewer_leaves_the_server_unaffected": 4.5,
        }),
    "tests/test_ffb.py": (
        "a force-feedback client beside a live server", {
            "test_the_wheel_follows_the_server_and_fades_to_the_spring_when_it_goes": 6.6,
        }),
    "tests/test_finite.py": (
        "a live server sent a 1e308 height map", {
            "test_a_1e308_height_map_sent_with_load_is_refused_and_nothing_non_finite_is_published": 3.9,  # noqa: E501
        }),
    "tests/test_fuzz.py": (
        "10 000 fuzzed payloads sent to a live server", {
            "test_live_server_survives_10000_fuzzed_payloads": 10.8,
        }),
    "tests/test_hill_queue_live.py": (
        "a live three-car queue on a 15 % hill, 40 s of real time", {
            "test_hill_queue_live_stops_1_m_behind_holds_and_follows": 54.2,
        }),
    "tests/test_holds.py": (
        "run-scenario of E5 as a process", {
            "test_run_scenario_e5_summary_agrees_with_the_history": 2.9,
        }),
    "tests/test_kernel_cache.py": (
        "kernel compiles into fresh caches and two checkouts", {
            "test_the_helper_compiles_no_step_and_the_server_finds_its_kernels": 7.7,
            "test_two_checkouts_share_one_cache": 4.3,
        }),
    "tests/test_load_errors.py": (
        "a live server loading a road of a million geometries", {
            "test_the_live_server_names_the_element_and_loads_a_road_of_a_million_geometries": 10.2,
        }),
    "tests/test_log_safety.py": (
        "a live server logging onto a size-limited or full file system", {
            "test_a_file_size_limit_cuts_the_command_log_and_the_loop_goes_on": 8.3,
            "test_a_full_disk_cuts_the_command_log_and_the_loop_goes_on": 7.3,
        }),
    "tests/test_manoeuvres.py": (
        "run-scenario of ISO 7401 with its figures", {
            "test_one_command_writes_the_figures_and_the_report[iso7401_step_steer-True]": 2.6,
        }),
    "tests/test_multicar_server.py": (
        "multi-car live servers with cars added and driven", {
            "test_a_car_added_and_removed_over_zenoh_while_the_world_runs": 2.5,
            "test_a_car_added_with_the_built_in_driver_drives_its_lane_and_bad_ones_change_nothing": 22.1,  # noqa: E501
            "test_a_single_car_list_driven_by_the_driver_drives": 2.4,
        }),
    "tests/test_multicar_session.py": (
        "a three-car live session recorded and replayed, with ROS 2 and Rerun", {
            "test_three_cars_recorded_live_replay_bit_for_bit_with_ros2_and_rerun": 19.3,
        }),
    "tests/test_powertrain.py": (
        "a live session reset at speed", {
            "test_a_live_session_reset_at_speed_drives_on": 2.5,
        }),
    "tests/test_readme_commands.py": (
        "the README's client commands as processes against its server", {
            "test_player_as_written": 2.1,
            "test_recorder_and_python_driver_as_written": 13.8,
        }),
    "tests/test_recorder_cars.py": (
        "a live world recorded by the recorder process", {
            "test_a_chosen_car": 2.6,
            "test_every_car_in_one_long_table": 4.1,
        }),
    "tests/test_ros2.py": (
        "the ROS 2 adapter process driving a live server for seconds", {
            "test_ackermann_reaches_and_holds_speed_then_stops_and_holds_on_10pct": 20.8,
            "test_cmd_vel_reaches_and_holds_speed_then_stops_and_holds_on_10pct": 9.9,
            "test_published_topics_as_rmw_zenoh_writes_them": 2.1,
        }),
    "tests/test_ros2_floods.py": (
        "floods into the ROS 2 adapter beside a live server", {
            "test_a_child_that_keeps_dying_is_restarted_with_a_doubling_delay": 3.6,
            # these six share one module fixture, the flood run (the first one's 26.7 s)
            "test_a_flood_does_not_make_the_servers_ticks_late[ackermann]": 0.0,
            "test_a_flood_does_not_make_the_servers_ticks_late[malformed]": 0.0,
            "test_a_flood_holds_the_odometry_rate[ackermann]": 26.7,
            "test_a_flood_holds_the_odometry_rate[malformed]": 0.0,
            "test_a_malformed_flood_is_logged_at_a_bounded_rate_with_counts": 0.0,
            "test_a_valid_flood_still_drives": 0.0,
        }),
    "tests/test_router.py": (
        "two servers joined by a router process", {
            "test_two_servers_joined_by_the_router_are_seen_and_driven_from_one_client": 3.8,
        }),
    "tests/test_scenario_live.py": (
        "OpenSCENARIO files played on a live server", {
            "test_each_shipped_xosc_runs_live[cut-in_simple]": 10.1,
            "test_each_shipped_xosc_runs_live[lane_change_crest]": 7.4,
            "test_person_drives_the_cut_in_ego_and_the_trigger_fires_on_it": 5.2,
            "test_storyboard_on_the_viewer_timeline": 9.3,
        }),
    "tests/test_security.py": (
        "TLS, access control and connection floods against live servers", {
            "test_a_get_config_flood_is_rate_limited_per_session_and_spares_the_driver": 2.0,
            "test_a_tcp_connect_burst_does_not_lock_authenticated_sessions_out": 2.6,
            "test_floods_from_another_host_do_not_lock_authenticated_sessions_out[held_silent]": 4.7,  # noqa: E501
            "test_floods_from_another_host_do_not_lock_authenticated_sessions_out[hello_then_garbage]": 3.0,  # noqa: E501
            "test_mutual_tls_rights_follow_the_certificate_name": 4.2,
            "test_no_session_without_valid_credentials": 4.5,
            "test_partial_client_hellos_from_other_sources_never_reach_zenoh_nor_lock_out": 5.9,
            "test_partial_client_hellos_from_the_drivers_own_source_do_not_bar_it": 14.6,
            "test_router_access_control_separates_servers_drivers_and_viewers": 5.1,
            "test_the_front_is_restarted_if_it_dies_and_the_port_stays_open": 4.0,
            "test_the_secured_config_lets_nobody_but_the_server_answer_the_controls": 3.2,
            "test_tls_client_that_trusts_the_ca_drives_and_plain_tcp_cannot_talk": 5.0,
            "test_view_with_the_tls_client_config_uses_its_endpoints_and_draws": 3.4,
            "test_viewer_reads_state_but_cannot_command_or_control": 2.0,
            "test_zenohs_listener_behind_the_front_is_reachable_by_the_front_alone": 3.8,
        }),
    "tests/test_server.py": (
        "live servers driven, isolated or replayed", {
            "test_liveliness_config_and_first_state": 2.6,
            "test_two_servers_are_isolated": 3.2,
        }),
    "tests/test_server_live_path.py": (
        "the live path under floods, wedged readers and hostile loads", {
            "test_a_second_server_for_the_same_vehicle_id_refuses_to_start": 3.9,
            "test_a_viewer_port_in_use_moves_to_a_free_port_and_its_death_is_logged": 3.0,
            "test_hostile_loads_never_stall_the_loop": 2.6,
            "test_states_go_inline_while_cheap_and_a_reader_that_stops_never_stalls_the_caller": 11.2,  # noqa: E501
        }),
    "tests/test_slow_subscriber.py": (
        "slow and stalled subscribers beside a live server", {
            "test_a_slow_subscriber_does_not_stop_the_others_states[default-project]": 8.8,
            "test_a_slow_subscriber_does_not_stop_the_others_states[default-zenoh_defaults]": 9.0,
            "test_a_slow_subscriber_does_not_stop_the_others_states[normal-project]": 8.9,
            "test_a_slow_subscriber_does_not_stop_the_others_states[normal-zenoh_defaults]": 8.3,
        }),
    "tests/test_state_schema.py": (
        "a live server and the recorder over every state field", {
            "test_a_live_server_publishes_every_field_and_the_recorder_records_each": 3.6,
        }),
    "tests/test_stop_text.py": (
        "a live server's stop statistics after seconds of running", {
            "test_stop_block_counts_ticks_since_the_reset_and_since_start_and_json_on_request": 3.3,
        }),
    "tests/test_suite_record.py": (
        "a pytest session as a process", {
            "test_whole_default_suite_is_recorded_and_a_selection_is_not": 4.6,
        }),
    "tests/test_sweep.py": (
        "Dask scheduler and worker processes", {
            "test_local_cluster_two_workers_identical_to_serial_and_run_scenario": 2.4,
            "test_resume_after_ctrl_c_runs_only_the_rest": 7.2,
            "test_scheduler_and_workers_on_loopback_a_killed_worker_loses_no_run": 20.9,
        }),
    "tests/test_sweep_plots.py": (
        "sweep figures rendered", {
            "test_axes_in_words_with_units_and_coinciding_points_visible": 2.6,
        }),
    "tests/test_terrain_recorder.py": (
        "a live server on a height map and the recorder", {
            "test_recorder_on_a_height_map_uses_the_reference_plane": 2.6,
        }),
    "tests/test_terrain_scenarios.py": (
        "run-scenario on OpenDRIVE roads with its plots", {
            "test_opendrive_scenario_history_places_the_car_on_the_road[terrain_crest_opendrive-crest-curve.xodr]": 12.7,  # noqa: E501
            "test_opendrive_scenario_history_places_the_car_on_the_road[terrain_velodrome_bank-velodrome.xodr]": 6.0,  # noqa: E501
        }),
    "tests/test_tls_front.py": (
        "the TLS front beside a live server", {
            "test_a_client_left_unanswered_by_zenoh_is_not_barred": 2.2,
        }),
    "tests/test_viewer_fps.py": (
        "a live viewer's recording", {
            "test_view_fps_decimates_the_saved_recording": 7.2,
        }),
    "tests/test_viewer_segments.py": (
        "a live viewer recording across loads and resets", {
            "test_live_rrd_has_one_recording_per_segment": 5.5,
        }),
    "tests/test_viewer_wait.py": (
        "viewers waiting for servers", {
            "test_a_token_without_an_answer_is_reported_as_a_busy_server": 2.0,
            "test_a_viewer_started_before_the_server_waits_for_it_and_draws_the_car": 6.0,
            "test_a_viewer_with_no_server_says_what_it_waited_for_without_a_traceback": 3.3,
        }),
    "tests/test_warm_imports.py": (
        "warm CLI commands as processes", {
            "test_a_warm_command_imports_only_what_it_uses[run-scenario-plots-rrd]": 3.6,
            "test_a_warm_command_imports_only_what_it_uses[tire-curves]": 2.1,
        }),
    "tests/test_web_view.py": (
        "the web view served and checked drawn", {
            "test_the_check_fails_for_a_blank_page_and_a_recording_without_the_car": 13.3,
            "test_the_web_viewer_draws_the_car_every_start[once]": 18.4,
        }),
    "tests/test_world.py": (
        "two processes compiling the step into an empty kernel cache (added at stop 41: "
        "37.1 s alone)", {
            "test_a_cars_bits_do_not_depend_on_which_process_compiled_its_kernels": 37.1,
        }),
    "tests/test_world_scenario.py": (
        "run-scenario of multi-car files with plots", {
            "test_a_start_off_the_road_is_refused_naming_the_file_and_the_car": 3.5,
            "test_run_scenario_writes_one_history_and_plots_every_car": 5.3,
        }),
    "tests/test_xosc_storyboard.py": (
        "run-scenario of an OpenSCENARIO storyboard", {
            "test_run_scenario_writes_the_storyboard_trace": 3.7,
        }),
}
"""file -> (what its long tests run, {test name: seconds in the recorded run at 84e0b9f})."""

PER_COMMIT: dict[str, str] = {
    "tests/test_readme.py::test_scenario_command_runs": "the README's headless example",
    "tests/test_server.py::test_throttle_moves_brake_stops_holds_on_10_percent_and_restarts":
        "the product's promise, live: drive, stop, hold on a 10 % hill and drive off",
    "tests/test_multicar_server.py::test_two_clients_drive_two_cars_and_each_sees_the_other":
        "two cockpits on one live world",
    "tests/test_security.py::test_default_server_holds_only_a_loopback_listener_and_no_udp_"
    "socket": "the default server's exposure",
    "tests/test_ros2.py::test_serve_ros2_flag_and_a_killed_adapter_is_restarted_within_2_s":
        "the ROS 2 adapter beside a live server",
    "tests/test_viewer_multicar.py::test_the_viewer_draws_every_car_and_follows_the_chosen_"
    "one": "the Rerun viewer of a live world",
    "tests/test_scenario_live.py::test_each_shipped_xosc_runs_live[hill_queue_15pct]":
        "an OpenSCENARIO file played live",
}
"""Tests of 2 s or more kept in the per-commit run (nodeid -> the path it is the one
end-to-end check of). Four tire-kernel tests took 8-14 s in the recorded run and are kept
too: I ran those four tests alone beside it, in the same checkout, and the recorded run
compiled their kernels again (most likely their cache files were rewritten meanwhile); in
the same session's other full runs they took under 0.6 s."""

LONG_NODEIDS: frozenset[str] = frozenset(
    f"{path}::{name}" for path, (_, tests) in LONG.items() for name in tests)


def per_commit_run(config: Any) -> bool:
    """Whether ``config``'s session is the per-commit run: the whole suite (pytest's
    ``testpaths``), no ``-m`` expression, ``SIMSERVER_SLOW`` unset."""
    import pytest

    return (config.args_source == pytest.Config.ArgsSource.TESTPATHS
            and not config.option.markexpr and os.environ.get("SIMSERVER_SLOW") != "1")


def mark(config: Any, items: list[Any]) -> None:
    """Mark the ``LONG`` tests among ``items`` ``long``; in the per-commit run, deselect
    them. When the whole suite is collected (pytest's ``testpaths``; before ``-k`` and
    ``--deselect`` select), raises ``pytest.UsageError`` for a name of ``LONG`` or
    ``PER_COMMIT`` whose file is collected but which names no test there (a file left out
    with ``--ignore`` is not checked; nor is a run of named files or tests, which may
    collect a part of a file)."""
    import pytest

    collected = {item.nodeid for item in items}
    files = {nodeid.split("::", 1)[0] for nodeid in collected}
    stale = sorted(nodeid for nodeid in LONG_NODEIDS | set(PER_COMMIT)
                   if nodeid.split("::", 1)[0] in files and nodeid not in collected)
    if stale and config.args_source == pytest.Config.ArgsSource.TESTPATHS:
        raise pytest.UsageError("tests/long_form.py names tests the suite does not have "
                                "(renamed or removed?): " + ", ".join(stale))
    long_items = []
    for item in items:
        if item.nodeid in LONG_NODEIDS:
            item.add_marker(pytest.mark.long)
            long_items.append(item)
    if long_items and per_commit_run(config):
        config.hook.pytest_deselected(items=long_items)
        items[:] = [item for item in items if item.nodeid not in LONG_NODEIDS]


# ------------------------------------------------------------------- the per-commit run's halves
BESIDE: dict[str, tuple[str, ...]] = {
    "in-process kernels: the tire models, slip, steering, terrain, roads, poses, the world "
    "step, contact, the driver model, the state record": (
        "tests/test_contact.py", "tests/test_driver.py", "tests/test_ground_display.py",
        "tests/test_hill_cars.py", "tests/test_history.py", "tests/test_multicar_logic.py",
        "tests/test_opendrive.py", "tests/test_openscenario.py", "tests/test_passivity.py",
        "tests/test_pose.py", "tests/test_road_position.py", "tests/test_scenarios.py",
        "tests/test_slip.py", "tests/test_stability.py", "tests/test_state_frame.py",
        "tests/test_steering.py", "tests/test_terrain.py", "tests/test_tir_file.py",
        "tests/test_tire_mf61.py", "tests/test_tire_registry.py", "tests/test_tire_simple.py",
        "tests/test_tire_split.py", "tests/test_tire_trust.py", "tests/test_world.py",
        "tests/test_world_message.py", "tests/test_world_replay.py",
        "tests/test_world_scenario.py"),
    "headless commands and batch runs: run-scenario, soak, tire-curves, compare, the bit "
    "comparison, sweeps on a local Dask cluster": (
        "tests/test_bit_compare.py", "tests/test_cli.py", "tests/test_compare.py",
        "tests/test_config_fuzz.py", "tests/test_hostile_inputs.py", "tests/test_keyframes.py",
        "tests/test_lane_change.py", "tests/test_manoeuvres.py", "tests/test_multisoak.py",
        "tests/test_soak.py", "tests/test_sweep.py", "tests/test_sweep_plots.py",
        "tests/test_sweep_worker.py", "tests/test_sweep_xosc.py"),
    "the repository itself: parameter tables, declared packages, import order, results": (
        "tests/test_dependencies.py", "tests/test_import_cycles.py",
        "tests/test_param_tables.py", "tests/test_results_doc.py"),
}
"""The per-commit run in two halves (``-n 2``: pytest-xdist's two workers, one half each,
:func:`half_of`): (what its files test -> the files) of the half that runs beside the
other. Its files start no simserver server and open no zenoh session: they compute in the
worker's own process or run headless command lines (and Dask's scheduler and workers, on
free loopback ports), so they cannot disturb the other half's live servers, whose 1 kHz
loops and real-time checks run in the main half as in one process (only the CPU is shared).
``tests/test_long_form.py`` checks that no file here starts a server or a zenoh session.
Chosen so that the two halves take about the same time on this machine: in a cold run of
this split (2026-12-08, one kernel cache for both workers then, with a plugin timing each
worker's tests) the main half's tests took 241 s, these 248 s."""

BESIDE_FILES: frozenset[str] = frozenset(f for files in BESIDE.values() for f in files)


def half_of(nodeid: str) -> str:
    """``"beside"`` for a test of a ``BESIDE`` file, else ``"main"``."""
    return "beside" if nodeid.split("::", 1)[0] in BESIDE_FILES else "main"


BESIDE_WORKER = "gw1"
"""The pytest-xdist worker the beside half runs on (the main half runs on ``gw0``)."""


def beside_kernel_cache() -> str:
    """The kernel cache of the beside half's worker (``SIMSERVER_CACHE_DIR``, below
    ``.pytest_cache/``: kept between runs, ignored by git).

    Each half compiles into its own cache, as two checkouts would, because the tire kernels'
    fused multiply-adds (``core.tire_layout.TIRE_JIT_OPTIONS``: fastmath ``contract``) make
    the last bits of a compiled kernel depend on which process compiled its callees: sharing
    one cache, the world of one compiled in the beside worker, which loaded the car's
    kernels from the main half's processes, differed from the car alone by 1e-21 at step 3
    (``tests/test_world.py``, 2 of 2 runs). Each half alone compiles like the one-process
    suite, whose bit-identity checks pass."""
    return str(Path(__file__).resolve().parents[1] / ".pytest_cache" / "simserver"
               / "beside-kernels")


def halves_scheduler(config: Any, log: Any) -> Any:
    """pytest-xdist's scheduler for the two halves: its load-by-scope scheduling with
    :func:`half_of` as the scope, so each half goes whole to one worker, in collection
    order: the beside half to ``BESIDE_WORKER``, the main half to the other
    (``tests/conftest.py``'s ``pytest_xdist_make_scheduler``). (xdist's own
    ``--dist loadgroup`` with ``xdist_group`` marks would group them, but pytest-xdist 3.8.0
    renames a test's node id to group it, which pytest 9.2 no longer lets it do: the marks
    are ignored and every test becomes a scope of its own.)"""
    from xdist.scheduler import LoadScopeScheduling

    class Halves(LoadScopeScheduling):
        def _split_scope(self, nodeid: str) -> str:
            return half_of(nodeid)

        def _assign_work_unit(self, node: Any) -> None:
            half = "beside" if node.gateway.id == BESIDE_WORKER else "main"
            if half in self.workqueue:  # this worker's half first (the base pops the oldest)
                self.workqueue.move_to_end(half, last=False)
            super()._assign_work_unit(node)

    return Halves(config, log)


def configure_worker(config: Any) -> None:
    """In the beside half's worker, before any kernel module is imported: its own kernel
    cache (:func:`beside_kernel_cache`), for its tests and the processes they start; the
    kernels of other source states there are deleted (about 9 MB each; ``SIMSERVER_CACHE_DIR``
    keeps one directory per state of ``simserver/core``'s sources)."""
    workerinput = getattr(config, "workerinput", None)
    if workerinput and workerinput.get("workerid") == BESIDE_WORKER:
        import shutil

        from simserver.core import CACHE_DIR_ENV, shared_cache_dir

        root = beside_kernel_cache()
        os.environ[CACHE_DIR_ENV] = root
        for other in Path(root).glob("simserver-*"):
            if other != shared_cache_dir(root):
                shutil.rmtree(other, ignore_errors=True)


def describe() -> str:
    """The long form as markdown: each file's reason and tests, the kept ones, the totals."""
    lines = ["| file | what makes its tests long | tests (seconds at 84e0b9f) |",
             "|---|---|---|"]
    for path, (why, tests) in LONG.items():
        lines.append(f"| `{path}` | {why} | " + "; ".join(
            f"`{name}` {seconds:.1f} s" for name, seconds in tests.items()) + " |")
    total = sum(s for _, tests in LONG.values() for s in tests.values())
    lines += ["", f"{len(LONG_NODEIDS)} tests, {total:.0f} s in the recorded run.", "",
              "Kept in the per-commit run although they take 2 s or more:", ""]
    lines += [f"- `{nodeid}`: {why}" for nodeid, why in PER_COMMIT.items()]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    sys.stdout.write(describe())
