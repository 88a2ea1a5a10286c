#!/usr/bin/env python
"""Run the reliability tests of issue #4 and write docs/RELIABILITY.md from their results.

Every case of the issue's list is mapped to the tests that exercise it (pytest node ids).
The tests run once, with a junit XML report in a temporary folder; the table's outcome and
"what the user sees" come from that report: the `message` properties the tests record with
`record_property`, or, for the Blender story, the line each step prints.  Other properties
are measurements and are listed under the table.  Nothing in the table is typed by hand:
a case without tests reads "not covered", and a gap in a case's coverage is stated.

    .venv/bin/python scripts/reliability_report.py                # CLI and core tests
    .venv/bin/python scripts/reliability_report.py --with-blender # also the bpy story (minutes)
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import re
import signal
import subprocess
import sys
import tempfile
import xml.etree.ElementTree as ElementTree
from dataclasses import dataclass, field, replace
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
OUTPUT = REPO / "docs" / "RELIABILITY.md"
BLENDER_FILE = "tests/test_blender_extension.py"
REL = "tests/test_reliability.py"
CKPT = "tests/test_checkpoint_cli.py"
LOADING = "tests/test_scene_loading.py"
GEOMETRY = "tests/test_geometry.py"
STORY = f"{BLENDER_FILE}::test_blender_story"


@dataclass
class Case:
    name: str
    tests: list[str]
    gap: str = ""  # what of the case no test covers


def _ids(prefix: str, *params: str) -> list[str]:
    return [f"{prefix}[{p}]" for p in params]


EVERY_PARAMETER = "[*]"  # a test's id ending so stands for each of its parametrized ids, as collected


def expanded(tests: list[str], existing: list[str]) -> list[str]:
    """`tests` with each "test[*]" replaced by the ids of its parametrized cases among `existing`
    (collected order), so a case added to a test's parameters joins its row without being copied
    here; a "test[*]" with none left stands, and shows as 'not found'."""
    out = []
    for test in tests:
        if test.endswith(EVERY_PARAMETER):
            prefix = test[: -len(EVERY_PARAMETER)] + "["
            out.extend([found for found in existing if found.startswith(prefix)] or [test])
        else:
            out.append(test)
    return out


CASES = [
    Case("A folder with no model", [
        *_ids(f"{REL}::test_broken_scene_folder", "no model"),
        f"{REL}::test_a_scene_folder_given_as_the_model_is_said",
        f"{REL}::test_a_file_that_is_no_model_is_not_called_a_damaged_checkpoint",
        *_ids(f"{CKPT}::test_cli_errors_are_one_line", "folder without a model"),
        f"{LOADING}::test_scene_folder_errors", f"{REL}::test_images_option_naming_a_file"]),
    Case("A truncated or corrupted `.bin`", [
        *_ids(f"{REL}::test_broken_scene_folder", "random cameras.bin", "truncated cameras.bin", "truncated images.bin",
              "truncated points3D.bin", "truncated frames.bin", "truncated rigs.bin", "absurd data count in frames.bin",
              "zero rotation in frames.bin", "zero rotation in images.txt",
              "zero rotation in frames.txt"),
        *_ids(f"{CKPT}::test_cli_errors_are_one_line", "random cameras.bin", "truncated images.bin")]),
    Case("A model whose values are damaged: two images of one name, a camera absurdly far off, an absurd camera size", [
        *_ids(f"{REL}::test_broken_scene_folder", "two images of one name", "camera far off", "camera width -48",
              "camera width 200000")]),
    Case("A model file the user may not read", [
        *_ids(f"{REL}::test_unreadable_model_file_is_a_permission_problem", "frames.bin", "images.bin")]),
    Case("A photo past Pillow's decompression-bomb limit", [
        *_ids(f"{REL}::test_broken_scene_folder", "photo header claiming 1200 MP"),
        f"{LOADING}::test_photos_past_pillows_bomb_limit_are_read_up_to_400_mp"]),
    Case("A model whose images are missing or only partly present", [
        *_ids(f"{REL}::test_broken_scene_folder", "all images missing", "some images missing", "unreadable image"),
        *_ids(f"{CKPT}::test_cli_errors_are_one_line", "missing images", "unreadable image"),
        f"{LOADING}::test_missing_images_are_counted", f"{LOADING}::test_photos_renamed_are_not_paired_by_their_order"]),
    Case("Images of other sizes than the model", [
        *_ids(f"{REL}::test_photos_in_other_formats_train", "other size than the model"),
        f"{REL}::test_photos_of_another_aspect_ratio",
        f"{LOADING}::test_smaller_copies_rescale_the_intrinsics",
        f"{LOADING}::test_model_cameras_at_a_shared_camera_are_rescaled_per_view",
        f"{LOADING}::test_another_aspect_ratio_is_rejected"]),
    Case("Grayscale, RGBA, 16-bit and EXIF-rotated photos", [
        *_ids(f"{REL}::test_photos_in_other_formats_train", "grayscale", "RGBA", "16-bit RGB", "16-bit grayscale",
              "EXIF-rotated JPEG"),
        f"{LOADING}::test_load_rgb_grayscale", f"{LOADING}::test_load_rgb_rgba_composites_on_black",
        f"{LOADING}::test_load_rgb_16_bit_is_scaled_not_clipped", f"{LOADING}::test_exif_rotated_jpeg",
        "tests/test_reconstruct.py::test_photos_in_a_camera_s_own_format_are_named"]),
    Case("An empty point cloud", [f"{REL}::test_empty_point_cloud", f"{GEOMETRY}::test_fit_slab_overrides_and_invalid_depths"]),
    Case("A model with a single image", [f"{REL}::test_single_image"]),
    Case("A capture that is not forward-facing (a ring of cameras)", [
        f"{REL}::test_ring_capture_is_not_forward_facing", f"{GEOMETRY}::test_360_ring_is_rejected_as_not_forward_facing"]),
    Case("A render camera behind the uv plane", [f"{REL}::test_render_camera_behind_the_uv_plane"]),
    Case("A render camera looking away from the scene", [f"{REL}::test_render_camera_looking_away"]),
    Case("A render camera with a zero-size image", [
        *_ids(f"{REL}::test_render_camera_with_zero_size_image", "zero width", "zero height"),
        *_ids(f"{CKPT}::test_cli_errors_are_one_line", "zero-size camera")]),
    Case("A corrupted or truncated checkpoint", [
        *_ids(f"{REL}::test_damaged_checkpoint", "truncated", "empty", "random bytes", "bytes flipped inside",
              "not a NeuLF checkpoint"),
        f"{REL}::test_damaged_checkpoint_message_names_a_way_out",
        f"{CKPT}::test_truncated_checkpoint", f"{CKPT}::test_leftover_temp_file",
        f"{CKPT}::test_atomic_write_failure_keeps_the_old_file",
        "tests/test_camera_path.py::test_video_of_a_model_whose_rig_is_damaged_ends_in_one_line",
        "tests/test_camera_path.py::test_a_damaged_rig_is_said_in_one_line[*]"]),
    Case("A damaged model folder: a model.pt zipfile cannot read, one we may not read, a checkpoint lacking keys, of "
         "other types (its train_config's values too) or of NaN weights, a members.json or starts.json of other types, a folder where model.pt, "
         "model.json or a render's PNG goes, a model.json of other types (read as none: resume rewrites it)", [
        f"{CKPT}::test_a_damaged_model_folder_is_one_line[*]",
        f"{CKPT}::test_a_render_onto_a_folder_names_it_and_keeps_it",
        f"{CKPT}::test_an_unreadable_model_file_is_not_called_damaged",
        *_ids(f"{CKPT}::test_resume_over_a_damaged_model_json", "metadata0", "metadata1")]),
    Case("A checkpoint from another scene", [
        f"{REL}::test_checkpoint_of_another_scene", f"{CKPT}::test_resume_with_another_scene",
        f"{REL}::test_a_reconstruction_changed_in_place_is_said_so",
        *_ids(f"{CKPT}::test_cli_errors_are_one_line", "render: another scene", "resume with another scene")]),
    Case("A checkpoint from another version", [
        *_ids(f"{REL}::test_damaged_checkpoint", "another version"), f"{CKPT}::test_other_version_format_and_damage"]),
    Case("Training killed with SIGKILL part-way: resuming loses at most one checkpoint interval", [
        f"{REL}::test_sigkill_during_training_loses_at_most_one_checkpoint_interval",
        f"{CKPT}::test_cli_sigint_cancels_and_saves", f"{STORY}[train_killed]"]),
    Case("The auto preset stopped or killed during its size search or before its model's first checkpoint: it "
         "resumes after its last scored size, trains a size chosen before at once, and a resumed model trains to its "
         "share of the budget with the search's record kept; the folders its candidates trained in are cleared", [
        "tests/test_auto_resume.py::test_a_search_killed_after_scored_candidates_goes_on_from_them[1]",
        "tests/test_auto_resume.py::test_a_search_killed_after_scored_candidates_goes_on_from_them[2]",
        "tests/test_auto_resume.py::test_a_size_chosen_before_the_final_models_first_checkpoint_trains_at_once",
        "tests/test_auto_resume.py::test_a_final_model_killed_after_a_checkpoint_resumes_to_its_share_of_the_budget",
        "tests/test_auto_resume.py::test_a_new_training_does_not_take_a_stopped_runs_search",
        "tests/test_auto_resume.py::test_the_search_trains_inside_the_model_folder_and_clears_a_killed_runs_folders"]),
    Case("A training stopped (SIGTERM, Ctrl-C) while it sets up (its photos read, the plane sweep): it ends at once, "
         "not after its first step, and says what was kept", [
        f"{REL}::test_a_stop_while_setting_up_ends_the_training_at_once",
        f"{REL}::test_a_stop_while_a_resumed_training_sets_up_keeps_the_model_as_it_was",
        f"{REL}::test_ctrl_c_while_a_python_train_call_sets_up_stops_it_at_once"]),
    Case("A training stopped (Ctrl-Z, `kill -STOP`, a scheduler's suspend) and continued: the time it stood still "
         "does not count against its minutes budget", [
        f"{REL}::test_time_stopped_does_not_count_against_a_minutes_budget",
        f"{REL}::test_the_step_clock_leaves_a_stop_out"]),
    Case("Cancel in Blender during training, then Train again", [
        f"{STORY}[train_cancel]", f"{STORY}[train_cancel_resume]",
        f"{CKPT}::test_cancel_then_resume_equals_straight_training",
        f"{CKPT}::test_a_paused_fast_field_resumes_from_its_weights_before_the_fill",
        "tests/test_starts.py::test_a_stop_before_the_choice_resumes_where_it_was[first]",
        "tests/test_starts.py::test_a_stop_before_the_choice_resumes_where_it_was[second]"]),
    Case("Blender quit while training, then reopened: the model and its progress are found again", [
        f"{STORY}[quit_while_training]", f"{REL}::test_reader_of_progress_goes_away",
        f"{REL}::test_a_second_training_of_the_same_model_folder_is_refused"]),
    Case("A render much larger than memory allows: chunking keeps peak memory bounded", [
        f"{REL}::test_large_render_has_bounded_peak_memory",
        "tests/test_render_chunks.py::test_in_chunks_halves_on_the_cpu_allocators_refusal_only",
        f"{REL}::test_running_out_of_memory_anywhere_is_one_line",
        "tests/test_blender_convert.py::test_worker_says_what_to_do_about_memory_and_missing_packages"]),
    Case("The .blend saved and reopened elsewhere: model paths are relative and resolve", [
        f"{STORY}[save_reload]", f"{STORY}[blend_moved]"]),
    Case("Another .blend opened while training: the training's end writes nothing into it", [
        f"{STORY}[open_other_while_training]"]),
    Case("A scene linked from another .blend: its model resolves beside that file; changing it is refused", [
        f"{STORY}[linked_scene]"]),
    Case("A Python in the preferences that is not one, or does not start: Train and Check say so", [
        f"{STORY}[user_errors]", f"{STORY}[dependencies_status]"]),
    Case("An output that cannot be written: a file in the way, a folder inside a file, a full disk", [
        f"{REL}::test_output_that_is_a_file_is_said_before_rendering",
        *_ids(f"{REL}::test_video_needs_a_video_file_name", "spiral", "a_folder"),
        f"{REL}::test_a_full_disk_is_one_line"]),
    Case("Options that are not numbers: NaN, inf, zero or negative where they must be positive, an absurd count, "
         "a training scale above 1", [
        *_ids(f"{REL}::test_numbers_that_are_not_numbers", "train --scale nan", "train --minutes nan",
              "train --checkpoint-seconds -5", "train --holdout-every -1", "train --depth-layers 100000",
              "train --scale 2", "render --scale inf", "render --aperture nan", "render --aperture inf",
              "video --frames -1", "video --fps 0"),
        f"{REL}::test_train_refuses_a_scale_above_one",
        *_ids(f"{CKPT}::test_cli_errors_are_one_line", "render: absurd scale", "video: absurd frame rate")]),
    Case("A camera file that is a folder, names two cameras alike, or whose K or size is not a pinhole's", [
        *_ids(f"{REL}::test_camera_json_problems", "a folder", "two cameras of one name", "K's last row not 0 0 1",
              "a width of 32.5", "a width of true"),
        f"{REL}::test_focus_pixel_outside_the_image",
        *_ids(f"{CKPT}::test_cli_errors_are_one_line", "camera a billion pixels wide", "camera 1e300 pixels wide",
              "cameras: empty name", "cameras: named only an extension", "cameras: lists nested deep")]),
    Case("Render options that were dropped without a word: --scale with --cameras, a focus without an aperture, "
         "a focus distance and a focus pixel together, a focal length without an f-stop, pixel samples while "
         "refocusing; --focus-pixel read between pixels", [
        f"{REL}::test_render_cameras_at_a_scale",
        f"{REL}::test_a_focus_without_an_aperture_renders_the_plain_pinhole",
        *_ids(f"{REL}::test_refocus_options_in_conflict", "a focus distance and a focus pixel",
              "a focal length without an f-stop"),
        f"{REL}::test_pixel_samples_while_refocusing_is_said",
        f"{REL}::test_focus_pixel_focuses_at_the_depth_map_s_pixel",
        f"{REL}::test_focus_pixel_takes_whole_pixels"]),
    Case("Reconstruct into a scene folder that holds a model: a failed run leaves it as it was, a same-named photo "
         "is never overwritten", [
        "tests/test_reconstruct.py::test_photo_of_same_name_never_overwritten",
        "tests/test_reconstruct.py::test_failed_run_leaves_existing_scene_untouched",
        "tests/test_reconstruct.py::test_failed_run_into_new_folder_leaves_nothing",
        "tests/test_reconstruct.py::test_failed_run_with_webp_leaves_no_photos"]),
    Case("Reconstruct killed outright (SIGKILL), stopped (SIGTERM), or run twice into one folder at once: the next "
         "run clears what the killed one left (a model it had completed put in place first); a stopped one names "
         "its signal and exits 143; the second is refused", [
        "tests/test_reconstruct.py::test_a_run_killed_outright_leaves_nothing_after_the_next",
        "tests/test_reconstruct.py::test_a_run_stopped_by_sigterm_says_so_and_exits_143",
        "tests/test_reconstruct.py::test_a_run_killed_between_its_two_renames_leaves_its_new_model_in_place",
        "tests/test_reconstruct.py::test_a_run_into_a_folder_another_run_reconstructs_is_refused",
        "tests/test_reconstruct.py::test_unclaimed_work_folders_are_removed_only_when_old",
        "tests/test_reconstruct.py::test_a_relative_scene_folder",
        f"{REL}::test_a_lock_whose_process_number_was_given_again_is_stale"]),
    Case("A damaged LLFF poses_bounds.npy, a COLMAP model with non-finite values, photos of another size than the "
         "others", [
        *_ids(f"{LOADING}::test_damaged_llff_rows_are_named", "nan height", "zero focal", "nan centre",
              "inf rotation", "not a rotation", "centre 1e300", "centre 1e9 off"),
        *_ids(f"{LOADING}::test_one_llff_row_of_unusable_bounds_is_left_out", "nan far", "near past far",
              "negative near"),
        f"{LOADING}::test_llff_bounds_unusable_in_every_row_need_the_depths_given",
        *_ids(f"{LOADING}::test_llff_arrays_of_another_shape_are_refused", "16 columns", "one dimension", "no rows",
              "text"),
        *_ids(f"{LOADING}::test_colmap_models_with_non_finite_poses_or_intrinsics_are_refused", "pose", "nan focal",
              "negative focal"),
        "tests/test_classic.py::test_photos_of_different_sizes_are_swept_together"]),
    Case("The Python API given what it cannot use: a negative or NaN budget, a camera whose K, R or t is not a "
         "pinhole's (shapes, NaN, a scaled R), a NaN or negative aperture; a render stopped by its callback; a "
         "camera past the captured surface; Ctrl-C in a train() call", [
        *_ids(f"{REL}::test_train_config_values_the_run_cannot_use", "steps=-5", "minutes=-1", "minutes=nan",
              "steps=2.5", "batch_size=-1", "holdout_every=-1"),
        f"{REL}::test_train_config_must_be_one",
        *_ids(f"{REL}::test_render_refuses_cameras_it_cannot_use", "t of 4 numbers", "K flat", "[R|t] as R",
              "R scaled", "R mirrored", "t NaN", "K zero", "K of text"),
        f"{REL}::test_render_takes_t_as_a_column_or_a_row",
        *_ids(f"{REL}::test_render_refuses_image_sizes_it_cannot_make", "80.7 wide", "True high", "zero wide",
              "too large", "a billion wide"),
        f"{REL}::test_a_render_that_does_not_fit_in_memory_is_one_line",
        *_ids(f"{REL}::test_refocus_values_it_cannot_use", "aperture nan", "aperture negative", "no lens samples"),
        f"{REL}::test_a_render_stopped_by_on_chunk_says_so",
        f"{REL}::test_a_camera_past_the_scene_sees_no_surface_behind_it",
        f"{REL}::test_a_refocused_pixel_takes_no_colour_from_a_surface_behind_the_camera",
        f"{REL}::test_render_view_gives_the_camera_s_warnings",
        f"{REL}::test_ctrl_c_in_a_python_train_call_saves_and_resumes",
        f"{REL}::test_ctrl_c_stops_a_python_train_call_between_steps",
        f"{REL}::test_numpy_numbers_in_a_train_config",
        f"{REL}::test_render_cameras_past_the_scene_are_said",
        f"{REL}::test_resume_with_nothing_to_resume_is_said"]),
    Case("A reconstruction far from its world's origin (georeferenced, 1e7 units off): renders, sweeps and trains "
         "(rays, camera neighbours, pose corrections) as near it", [
        *_ids("tests/test_far_origin.py::test_a_camera_far_from_the_origin_renders_as_near_it", "pinhole",
              "pixel samples", "refocus"),
        "tests/test_far_origin.py::test_a_registered_view_far_from_the_origin_renders_as_near_it",
        "tests/test_far_origin.py::test_the_plane_sweep_far_from_the_origin_sweeps_as_near_it",
        "tests/test_far_origin.py::test_training_rays_and_camera_centres_far_from_the_origin_are_as_near_it"]),
    Case("Blender: an artist's own settings kept (a copy of a capture camera, the scene camera, size and colours "
         "through a re-import, the output through Render Video, a second scene's capture), an orthographic camera "
         "refused before a video, DOF on a bone or an object behind the camera as Blender focuses", [
        f"{STORY}[artist_settings]"]),
    Case("Blender: the capture's own objects stay its own (a renamed capture camera, a Shift+D copy of the root, a "
         "root deleted and imported again), a root scaled unevenly refused, a capture camera framing otherwise than "
         "the scene said; the first scene camera of the photos' most common size", [
        f"{STORY}[capture_identity]",
        "tests/test_blender_convert.py::test_a_root_scaled_unevenly_is_refused",
        "tests/test_blender_convert.py::test_the_first_scene_camera_is_of_the_photos_most_common_size"]),
    Case("--resume (and train(resume=True) from Python) with options other than the model's: said, the model kept "
         "(a second member the resume starts included: it trains on the first one's views, not its held-out ones)", [
        f"{REL}::test_resume_says_which_asked_options_the_model_keeps",
        f"{REL}::test_resume_from_python_says_which_options_the_model_keeps",
        f"{REL}::test_a_member_started_by_a_resume_trains_on_the_first_members_views"]),
    Case("A model trained on another images folder than the scene's default (LLFF's images_N): eval, render and "
         "--resume read its own photos, or say so; views named twice, or among held-out, scored once; photos "
         "replaced since training (same names and sizes) said by eval and resume", [
        f"{REL}::test_eval_render_and_resume_read_the_photos_the_model_trained_on",
        f"{REL}::test_photos_replaced_since_training_are_said",
        f"{REL}::test_eval_scores_each_view_once_and_takes_held_out_among_names",
        f"{REL}::test_blender_import_with_a_model_reads_its_photos"]),
    Case("The training lifecycle: a model whose checkpoint.pt was deleted (model.pt kept) neither trained over nor "
         "resumed, an older model's members not taken by a new one, the auto preset refusing before its search, a "
         "closed terminal (SIGHUP) saving, a seed, batch or split asked on --resume said, a camera edited with its "
         "centre kept said, a failed write naming its file, the demo failing where its video fails", [
        f"{REL}::test_a_model_without_its_checkpoint_is_neither_trained_over_nor_resumed",
        f"{REL}::test_a_new_model_does_not_take_an_older_one_s_members",
        f"{REL}::test_the_auto_preset_refuses_a_trained_folder_before_its_search",
        f"{REL}::test_a_closed_terminal_saves_the_training",
        f"{REL}::test_resume_says_a_seed_a_split_or_a_batch_the_model_keeps",
        f"{REL}::test_a_camera_edited_with_its_centre_kept_is_said",
        f"{REL}::test_a_failed_write_names_its_file",
        f"{REL}::test_the_demo_fails_where_its_video_fails",
        f"{REL}::test_the_cancel_line_names_the_member_that_was_training",
        f"{REL}::test_a_model_records_its_scene_folder_whole"]),
    Case("Degenerate captures: stray points near the lens, a flat subject, photos taken twice from one place, a "
         "tripod panorama, photos smaller than SSIM's window, blank photos (a lens cap)", [
        "tests/test_degenerate_captures.py::test_stray_points_near_the_lens_do_not_place_the_slab",
        "tests/test_degenerate_captures.py::test_real_content_near_the_lens_is_not_taken_for_strays",
        "tests/test_degenerate_captures.py::test_blank_photos_are_named",
        "tests/test_degenerate_captures.py::test_a_flat_subject_trains",
        "tests/test_degenerate_captures.py::test_photos_taken_twice_from_one_place_train",
        "tests/test_degenerate_captures.py::test_a_tripod_panorama_is_said_and_not_pose_checked",
        "tests/test_degenerate_captures.py::test_ssim_of_photos_smaller_than_its_window"]),
    Case("Captures of mixed cameras: a distorted view refocused through its own lens, a photo far wider than the "
         "others said, a view that sees past the capture said by render and eval, a camera path's camera, "
         "fractional frame rates", [
        "tests/test_refocus.py::test_a_refocused_registered_view_keeps_its_own_lens_distortion",
        "tests/test_refocus.py::test_a_registered_view_s_depth_pick_reads_its_own_depth_map",
        "tests/test_mixed_cameras.py::test_a_photo_that_sees_far_wider_than_the_others_is_said",
        "tests/test_mixed_cameras.py::test_a_registered_view_that_sees_past_the_capture_is_said",
        "tests/test_mixed_cameras.py::test_eval_reports_each_view_s_warnings",
        "tests/test_mixed_cameras.py::test_a_camera_path_takes_the_most_common_photo_size_and_the_median_focal_length",
        "tests/test_mixed_cameras.py::test_a_video_takes_a_fractional_frame_rate"]),
    Case("Blender's worker: a model whose second member trained on is loaded again (it rendered stale); Check "
         "needs every module training imports (a Python without Pillow passed)", [
        "tests/test_api_inputs.py::test_the_worker_reloads_a_model_whose_second_member_trained_on",
        "tests/test_api_inputs.py::test_the_worker_s_check_needs_every_module_training_imports"]),
    Case("Blender's worker and render: a video whose frame fails (in the UI too) leaves no video that passes for "
         "the whole path; a bug in a frame ends the render in one line; a missing package, packages of another "
         "Python version, a Python older than 3.10 and a killed process are named; Load Model whose capture "
         "cannot be imported attaches the model with a warning; Render Camera runs on a thread that can be cancelled", [
        f"{STORY}[video_cut_short]", f"{STORY}[user_errors]",
        "tests/test_blender_convert.py::test_explain_failure",
        "tests/test_blender_convert.py::test_an_older_python_is_told_before_any_import_fails",
        "tests/test_blender_convert.py::test_a_killed_process_is_said_to_be_killed",
        "tests/test_blender_convert.py::test_thread_call_ends_with_result_error_or_cancel",
        f"{STORY}[render_camera_thread]"]),
    Case("A real-size capture in Blender (audit, 2026-12-02): a minutes budget spent before 200 steps (a busy "
         "machine's plane sweep had taken the whole minute: \"finished\" at 0 steps); an f-stop that hardly blurs at "
         "the reconstruction's units; a second scene's import of a capture whose folder holds a model; Load Model "
         "importing the capture", [
        f"{CKPT}::test_a_minutes_budget_that_ends_before_training_is_said",
        f"{CKPT}::test_a_size_search_candidate_short_by_design_is_not_said_barely_trained",
        "tests/test_blender_convert.py::test_train_job_parses_events", f"{STORY}[focus_at]", f"{STORY}[user_errors]"]),
    Case("Two trainings of one folder at once (processes racing for a new or a stale lock, a training started during "
         "the auto preset's size search): one trains, the others are refused; a model folder whose path leaves no "
         "room for a checkpoint is refused before training", [
        "tests/test_lock.py::test_processes_racing_for_a_lock_never_hold_it_together[nobody]",
        "tests/test_lock.py::test_processes_racing_for_a_lock_never_hold_it_together[a process that is gone]",
        "tests/test_lock.py::test_a_lock_is_released_only_while_it_is_still_this_process",
        "tests/test_lock.py::test_a_lock_that_cannot_be_deleted_leaves_the_error_that_ended_the_training",
        "tests/test_lock.py::test_a_lock_being_written_is_not_taken_for_a_stale_one",
        "tests/test_lock.py::test_the_thread_holding_a_lock_takes_it_again_and_others_are_refused",
        "tests/test_lock.py::test_the_auto_presets_search_holds_the_lock",
        "tests/test_lock.py::test_a_model_folder_path_too_long_for_the_checkpoint_is_refused_before_training",
        "tests/test_lock.py::test_an_empty_lock_dated_in_the_future_is_not_waited_for",
        "tests/test_lock.py::test_a_takeover_that_vanished_while_read_is_not_deleted",
        *_ids("tests/test_lock.py::test_a_dead_processes_takeover_is_deleted", "by a process that is gone",
              "unwritten long ago")]),
    Case("Outputs of render, eval and video: never written over the scene's photos; a rig's views that share a "
         "stem each get their own file; whole files or none when stopped; a video stopped part-way keeps the earlier "
         "one and says where its frames are; SIGTERM ends in one line; ~ is the home folder; eval makes nothing in a "
         "folder that holds no model", [
        *_ids("tests/test_outputs.py::test_renders_never_replace_the_scene_s_photos", "render into images",
              "eval into images", "render from inside images", "render cameras into images"),
        *_ids("tests/test_outputs.py::test_renders_never_replace_another_photo_folder_of_the_scene", "render", "eval"),
        "tests/test_outputs.py::test_eval_of_a_model_file_writes_beside_it",
        "tests/test_outputs.py::test_a_video_killed_outright_leaves_no_temporary_after_the_next",
        "tests/test_outputs.py::test_a_rig_s_views_that_share_a_stem_each_get_their_own_render",
        "tests/test_outputs.py::test_a_rig_s_photo_folder_is_refused_as_out",
        "tests/test_outputs.py::test_renders_and_eval_files_are_replaced_whole",
        f"{REL}::test_an_eval_stopped_between_its_two_tables_leaves_no_eval_json_of_another_run",
        "tests/test_outputs.py::test_a_render_stopped_by_sigterm_says_one_line_and_leaves_whole_files",
        f"{CKPT}::test_a_signal_as_the_temporary_is_made_leaves_none_behind",
        *_ids("tests/test_outputs.py::test_a_video_stopped_part_way_keeps_the_earlier_video", "SIGTERM", "SIGINT"),
        "tests/test_outputs.py::test_tilde_is_the_home_folder_for_every_output",
        *_ids("tests/test_outputs.py::test_eval_of_a_folder_that_is_not_a_model_leaves_nothing_in_it", "scene",
              "photos", "empty")]),
    Case("A camera path that looks past the captured region (a lens wider than the capture's): said before "
         "rendering, by the CLI's video and Blender's Spiral Camera Path, with the lens (mm) that keeps it inside", [
        "tests/test_camera_path.py::test_the_share_is_the_renderers_own_count",
        "tests/test_camera_path.py::test_the_lens_that_keeps_the_path_inside_is_the_shortest",
        "tests/test_camera_path.py::test_spiral_for_blender_names_the_lens",
        "tests/test_camera_path.py::test_video_says_frames_past_the_capture", f"{STORY}[spiral_video]"]),
    Case("Apple's MPS: a torch whose MPS lacks border-padded grid_sample (or its gradient) is refused in one line "
         "(passed over when choosing the fastest device); its 'Invalid buffer size' counts as out of memory; no "
         "float64 reaches the device (checked on a CPU stand-in that refuses it as MPS does)", [
        "tests/test_mps_portability.py::test_asking_for_an_mps_that_falls_short_is_refused_in_one_line",
        "tests/test_mps_portability.py::test_the_default_device_passes_over_an_mps_that_falls_short_with_a_note",
        *_ids("tests/test_render_chunks.py::test_a_field_the_mps_allocator_refuses_renders_in_halves",
              "MPS backend out of memory", "Invalid buffer size"),
        "tests/test_mps_portability.py::test_training_on_the_stand_in_keeps_float64_off_the_device",
        "tests/test_mps_portability.py::test_fitting_a_held_out_pose_keeps_float64_off_the_device",
        "tests/test_mps_portability.py::test_the_eval_command_fits_poses_on_the_stand_in",
        *_ids("tests/test_mps_portability.py::test_rendering_colour_and_depth_keeps_float64_off_the_device", "full",
              "half")],
         gap="nothing here has run on a Mac: the float64 check runs on a CPU stand-in, and the probe and MPS's "
             "out-of-memory words on faked devices"),
    Case("A second reader's Blender audit (2026-12-02): another program's model.json in the model folder is neither "
         "loaded nor trained over; a model.json damaged beside its checkpoint is written again from it (Train had "
         "counted from step 0); a video path under a file; '//' paths in a .blend never saved; a camera under a "
         "turned, unevenly scaled parent; a render size of 0 pixels; an Image Scale (--scale) that leaves photos of "
         "a few pixels; a render before a training's first checkpoint; a photo given as the video; the core's "
         "command-line advice said in Blender's words", [
        f"{REL}::test_another_programs_model_json_is_not_trained_over[*]",
        f"{REL}::test_a_scale_that_leaves_photos_of_a_few_pixels_is_refused[*]",
        f"{CKPT}::test_a_lost_model_json_is_written_again_from_its_checkpoint",
        f"{CKPT}::test_a_saved_config_of_the_declared_types_passes_and_others_are_named",
        "tests/test_blender_convert.py::test_a_sheared_camera_is_refused_and_an_unevenly_scaled_one_is_not",
        "tests/test_blender_convert.py::test_the_cores_advice_in_blenders_words",
        "tests/test_reconstruct.py::test_frames_refuses_what_it_cannot_use", f"{STORY}[user_errors]"]),
    Case("No network access unless the user asks for the dependency install, with the declared permission", [
        f"{REL}::test_no_network_unless_the_user_installs", f"{STORY}[install_dependencies]"]),
]


# ----------------------------------------------------------------------------- running pytest


@dataclass
class Result:
    outcome: str                      # passed, failed, error, skipped, xfailed, not run, not found
    messages: list[str] = field(default_factory=list)
    measured: list[tuple[str, str]] = field(default_factory=list)
    detail: str = ""


def pytest_command(*args: str) -> list[str]:
    return [sys.executable, "-m", "pytest", "-p", "no:cacheprovider", *args]


def collect(files: list[str]) -> list[str]:
    """Node ids that exist now, in pytest's order (a renamed test shows as 'not found', not as a pass)."""
    run = subprocess.run(pytest_command("--collect-only", "-q", *files), cwd=REPO, capture_output=True, text=True,
                         env=test_environment())
    return [line.strip() for line in run.stdout.splitlines() if "::" in line]


def test_environment() -> dict:
    env = dict(os.environ)
    env.setdefault("OMP_NUM_THREADS", "1")  # shared machines: keep the timings comparable
    return env


def run_tests(node_ids: list[str], junit: Path) -> int:
    args = pytest_command("-q", f"--junitxml={junit}", "-o", "junit_logging=system-out", "-o",
                          "junit_family=xunit1", *node_ids)
    # Ctrl-C as a terminal's foreground command has it: the report run as a background job of a
    # non-interactive shell (`cmd &`) inherits SIGINT ignored, and the real-Ctrl-C test skipped.
    restore = (lambda: signal.signal(signal.SIGINT, signal.SIG_DFL)) if os.name == "posix" else None
    return subprocess.run(args, cwd=REPO, env=test_environment(), preexec_fn=restore).returncode


def node_id(case: ElementTree.Element) -> str:
    module = case.get("classname", "")
    parts = module.split(".")
    # classname is module.path[.Class]; test files live in tests/ and hold no classes here.
    return "/".join(parts) + ".py::" + case.get("name", "")


def outcome_of(case: ElementTree.Element) -> tuple[str, str]:
    for tag in ("failure", "error"):
        found = case.find(tag)
        if found is not None:
            return ("failed" if tag == "failure" else "error"), (found.get("message") or "").strip()
    skipped = case.find("skipped")
    if skipped is not None:
        kind = "xfailed" if skipped.get("type") == "pytest.xfail" else "skipped"
        return kind, (skipped.get("message") or "").strip()
    return "passed", ""


def read_junit(path: Path) -> dict[str, Result]:
    results = {}
    for case in ElementTree.parse(path).getroot().iter("testcase"):
        outcome, detail = outcome_of(case)
        result = Result(outcome, detail=detail)
        for prop in case.iter("property"):
            name, value = prop.get("name"), prop.get("value", "")
            if name == "message":
                result.messages.append(value)
            else:
                result.measured.append((name, value))
        test = node_id(case)
        if test.startswith(STORY):
            result.messages.extend(story_line(test, case))
        results[test] = result
    return results


def story_line(test: str, case: ElementTree.Element) -> list[str]:
    """The line a Blender story step prints: "<step>: what happened" (its system-out)."""
    step = test[test.index("[") + 1:-1]
    printed = (case.findtext("system-out") or "").splitlines()
    return [line for line in printed if line.startswith(f"{step}: ")][-1:]


# ----------------------------------------------------------------------------- the document


TEMP_PATH = re.compile(r"/\S*?/pytest-of-[^/\s]+/pytest-\d+/")  # pytest's temporary folders, shortened


def cell(text: str, limit: int = 400) -> str:
    text = TEMP_PATH.sub("TMP/", " ".join(text.split())).replace("|", "\\|")
    return text if len(text) <= limit else text[: limit - 1] + "…"


def case_outcome(case: Case, results: dict[str, Result]) -> str:
    if not case.tests:
        return "not covered"
    outcomes = [results[t].outcome for t in case.tests]
    if any(o in ("failed", "error", "not found") for o in outcomes):
        return "**FAILED**"
    ran = [o for o in outcomes if o not in ("not run", "skipped")]
    if not ran:
        return "not run"
    label = "passed"
    if "xfailed" in ran:  # say how many pass, so one known failure does not hide the rest
        label = f"{ran.count('passed')} passed, {ran.count('xfailed')} known failure(s) (xfail)"
    return label + (" (partly)" if case.gap else "")


def test_cell(test: str, result: Result) -> str:
    short = test.replace("tests/", "")
    return f"`{short}` {result.outcome}"


def message_cell(case: Case, results: dict[str, Result]) -> str:
    lines = []
    for test in case.tests:
        result = results[test]
        lines.extend(result.messages)
        if result.outcome in ("failed", "error", "xfailed") and result.detail:
            lines.append(f"[{result.outcome}: {result.detail.splitlines()[0]}]")
    unique = list(dict.fromkeys(cell(line) for line in lines))
    return "<br>".join(unique) if unique else "(no message recorded by these tests)"


def document(cases: list[Case], results: dict[str, Result], *, with_blender: bool, exit_code: int,
             started: datetime.datetime) -> str:
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO, capture_output=True, text=True).stdout.strip()
    dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=REPO, capture_output=True,
                           text=True).stdout.strip()
    out = [
        "# Reliability: cases and outcomes",
        "",
        "Generated by `scripts/reliability_report.py` from a pytest run's junit XML -- do not edit by hand.",
        f"Run {started:%Y-%m-%d %H:%M} UTC on commit {commit}{' with local changes' if dirty else ''}, "
        f"Python {platform.python_version()}, {platform.system()} {platform.machine()}; pytest exit status {exit_code}; "
        f"Blender story {'run' if with_blender else 'not run (pass --with-blender; it needs bpy and takes minutes)'}.",
        "",
        "Each case is issue #4's list.  Outcome: passed, **FAILED**, known failure (a strict xfail that names the fix "
        "it waits for), not run, or not covered; \"(partly)\" when the tests leave part of the case out (see Gaps).  "
        "The last column is what the user sees, as recorded by the tests.",
        "",
        "| # | Case | Tests | Outcome | What the user sees |",
        "|---|------|-------|---------|--------------------|",
    ]
    for number, case in enumerate(cases, 1):
        tests = "<br>".join(test_cell(t, results[t]) for t in case.tests) or "none"
        out.append(f"| {number} | {case.name} | {tests} | {case_outcome(case, results)} | {message_cell(case, results)} |")
    gaps = [(n, c) for n, c in enumerate(cases, 1) if c.gap or not c.tests]
    out += ["", "## Gaps", ""]
    out += [f"- {n}. {c.name}: {c.gap or 'not covered'}." for n, c in gaps] or ["- none"]
    out += ["", "## Measured", ""]
    measured = [(t, name, value) for t in dict.fromkeys(t for c in cases for t in c.tests)
                for name, value in results[t].measured]
    out += [f"- `{t.replace('tests/', '')}`: {name} = {value}" for t, name, value in measured] or ["- nothing measured"]
    out.append("")
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--with-blender", action="store_true", help="also run the Blender story (needs bpy; minutes)")
    parser.add_argument("--output", type=Path, default=OUTPUT)
    args = parser.parse_args(argv)
    started = datetime.datetime.now(datetime.timezone.utc)

    existing = collect(sorted({t.split("::")[0] for case in CASES for t in case.tests}))
    cases = [replace(case, tests=expanded(case.tests, existing)) for case in CASES]
    wanted = list(dict.fromkeys(t for case in cases for t in case.tests))
    present = set(existing)
    to_run = [t for t in wanted if t in present and (args.with_blender or not t.startswith(BLENDER_FILE))]
    with tempfile.TemporaryDirectory() as tmp:
        junit = Path(tmp) / "junit.xml"
        exit_code = run_tests(to_run, junit)
        results = read_junit(junit) if junit.is_file() else {}
    for test in wanted:
        if test not in results:
            results[test] = Result("not found" if test not in present else "not run")
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(document(cases, results, with_blender=args.with_blender, exit_code=exit_code,
                                    started=started))
    print(f"wrote {args.output}")
    failed = [t for t in to_run if results[t].outcome in ("failed", "error")]
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
