"""The basin tools (``render.inverse.basin``: block-mean pyramids, coarse to fine, greedy
search) and the reconstruction experiments (``render.inverse.reconstruction``), at tiny
sizes: the loss drops and the metrics are computed right."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import minidiff as md
import render
from render.inverse import reconstruction
from render.inverse.basin import coarse_to_fine, downsample, greedy_search, multi_start, resized
from render.inverse.experiments import run_camera_calibration
from render.inverse.reconstruction import (
    pose_problem,
    pose_starts,
    rotation_error_degrees,
    run_pose,
)


def test_downsample_is_the_block_mean():
    image = np.arange(4 * 6 * 3, dtype=float).reshape(4, 6, 3)
    small = downsample(image, 2)
    assert small.shape == (2, 3, 3)
    assert np.array_equal(small[1, 2], image[2:4, 4:6].mean(axis=(0, 1)))
    with pytest.raises(ValueError, match="factor 4 does not divide the image size 4x6"):
        downsample(image, 4)
    with pytest.raises(ValueError, match="factor must be an int >= 1"):
        downsample(image, 0)


def test_resized_shares_the_camera_tensors():
    scene = render.paper_scene(32, 32)
    small = resized(scene, 8, 8)
    assert (small.camera.width, small.camera.height) == (8, 8)
    assert small.camera.position is scene.camera.position and small.objects == scene.objects


def test_rotation_error_is_the_angle_between_rotations():
    truth = np.array([0.0, 30.0, 0.0])
    turned = np.degrees((Rotation.from_rotvec(np.radians([10.0, 0, 0])) *
                         Rotation.from_rotvec(np.radians(truth))).as_rotvec())  # fmt: skip
    assert rotation_error_degrees(turned, truth) == pytest.approx(10.0, abs=1e-9)
    assert rotation_error_degrees(np.array([0.0, 0.0, 350.0])) == pytest.approx(10.0, abs=1e-9)


def test_pose_problem_starts_where_it_says():
    scene, (rotation, translation), target, extent = pose_problem(16, 45.0, 3)
    assert rotation_error_degrees(rotation.data) == pytest.approx(45.0, abs=1e-9)
    assert np.linalg.norm(translation.data) == pytest.approx(0.1 * extent, rel=1e-12)
    assert target.shape == (16, 16, 3)


def test_greedy_search_keeps_the_best_and_counts_its_renders():
    scene, params, target, extent = pose_problem(32, 30.0, 1)

    def propose(rng, best, progress):  # random steps around the best
        return [best[0] + rng.normal(size=3) * 10.0, best[1] + rng.normal(size=3) * 0.1]

    runs = [greedy_search(scene, params, target, propose, renders=12, factor=2, seed=5)
            for _ in range(1)]  # fmt: skip
    result = runs[0]
    assert result.renders == 13  # the start and 12 proposals
    assert result.loss <= result.start_loss
    losses = [loss for _, loss in result.accepted]
    assert losses == sorted(losses, reverse=True)  # each accepted one lowered the loss
    with md.no_grad():  # the parameters hold the best: its loss, rendered again
        again = render.image_loss(render.render(resized(scene, 16, 16)), downsample(target, 2))
    assert again.item() == pytest.approx(result.loss, rel=1e-12)
    with pytest.raises(ValueError, match="renders must be an int >= 0"):
        greedy_search(scene, params, target, propose, renders=-1)


def test_coarse_to_fine_runs_each_stage_at_its_size():
    scene, params, target, _ = pose_problem(32, 10.0, 2)
    sizes = []
    histories = coarse_to_fine(scene, params, target, factors=(4, 1), iters=(3, 2), lr=[1.0, 0.02],
                               quiet=True, callback=lambda it, loss, image, h: sizes.append(
                                   image.shape[0]))  # fmt: skip
    assert [h.iterations for h in histories] == [3, 2]
    assert sizes == [8] * 4 + [32] * 3
    with pytest.raises(ValueError, match="factors and iters"):
        coarse_to_fine(scene, params, target, factors=(2,), iters=(1, 2))


def test_pose_starts_turn_the_start_about_six_axes():
    rotation, translation = np.array([10.0, -20.0, 5.0]), np.array([0.1, 0.2, 0.3])
    starts = pose_starts(rotation, translation, 6, turn=30.0)
    assert len(starts) == 7 and np.array_equal(starts[0][0], rotation)
    for k, (turned, shift) in enumerate(starts[1:]):
        assert rotation_error_degrees(turned, rotation) == pytest.approx(30.0, abs=1e-9)
        axis = np.vstack([np.eye(3), -np.eye(3)])[k]  # turned = R(30 deg about axis) * start
        step = Rotation.from_rotvec(np.radians(turned)) * Rotation.from_rotvec(
            np.radians(rotation)).inv()  # fmt: skip
        assert np.allclose(step.as_rotvec(), np.radians(30.0) * axis, atol=1e-12)
        assert np.array_equal(shift, translation)
    assert len(pose_starts(rotation, translation, 0)) == 1
    with pytest.raises(ValueError, match="count must be an int in 0..6"):
        pose_starts(rotation, translation, 7)


def test_multi_start_runs_each_start_small_and_keeps_the_lowest_loss():
    scene, params, target, _ = pose_problem(32, 30.0, 1)
    starts = pose_starts(params[0].data, params[1].data, 2)
    sizes = []
    kwargs = {"lr": [1.0, 0.02], "quiet": True, "render_kwargs": {"antialias": True}}
    kwargs["callback"] = lambda it, loss, image, h: sizes.append(image.shape[0])
    result = multi_start(scene, params, target, starts, iters=3, factor=2, **kwargs)
    assert sizes == [16] * (3 * 4)  # three starts, 3 updates and a last evaluation each
    assert result.renders == 12 and len(result.losses) == 3
    assert result.best == int(np.argmin(result.losses))
    with md.no_grad():  # the parameters hold where the best start ended
        again = render.image_loss(render.render(resized(scene, 16, 16), antialias=True),
                                  downsample(target, 2))  # fmt: skip
    assert again.item() == pytest.approx(result.losses[result.best], rel=1e-9)
    with pytest.raises(ValueError, match="at least one start"):
        multi_start(scene, params, target, [])


def test_default_pose_run_starts_small_then_goes_on_at_full_size(monkeypatch):
    # the default multi-start's mechanics, with 2 iterations per start instead of 40: the
    # stage runs at POSE_START_SIZE pixels, then the full-size gradients go on from the
    # start with the lowest loss
    monkeypatch.setattr(reconstruction, "POSE_START_ITERS", 2)
    monkeypatch.setattr(reconstruction, "POSE_START_SIZE", 16)
    seen = []
    original = reconstruction.optimize

    def recording(scene, params, target, **kwargs):
        seen.append((target.shape[0], kwargs["render_kwargs"]["antialias"], kwargs["max_iters"]))
        return original(scene, params, target, **kwargs)

    monkeypatch.setattr("render.inverse.basin.optimize", recording)
    monkeypatch.setattr(reconstruction, "optimize", recording)
    result = run_pose(size=32, angle=30.0, seed=100, iters=3, antialias=True)
    assert seen == [(16, True, 2)] * 7 + [(32, True, 3)]
    assert result["starts"] == 6 and len(result["start_losses"]) == 7
    assert result["start_renders"] == 7 * 3 and result["search_renders"] == 0
    assert result["start_kept"] == int(np.argmin(result["start_losses"]))
    assert result["seconds"] >= result["start_seconds"] > 0
    with pytest.raises(ValueError, match="starts and search are alternatives"):
        run_pose(size=32, iters=1, search=2, starts=6)


def test_pose_run_lowers_the_loss_and_reports_its_errors():
    result = run_pose(size=32, angle=10.0, seed=0, iters=12, antialias=True, starts=0)
    assert result["final_loss"] < 0.7 * result["initial_loss"]
    assert result["rotation_error_after_search"] == pytest.approx(10.0, abs=1e-9)
    assert result["rotation_error_degrees"] == rotation_error_degrees(np.array(result["rotation"]))
    moved = np.linalg.norm(result["translation"]) / result["extent"] * 100
    assert result["translation_error_percent"] == pytest.approx(moved, rel=1e-12)
    assert result["success"] == (result["rotation_error_degrees"] < 1.0
                                 and result["translation_error_percent"] < 1.0)  # fmt: skip


def test_camera_search_counts_its_renders_in_the_time():
    run = run_camera_calibration(size=32, iters=3, seed=42, angle=30.0, search=6, antialias=True)
    metrics = run.metrics
    assert metrics["search_renders"] == 7
    assert metrics["seconds_total"] >= metrics["search_seconds"] > 0
    assert run.initial.shape == (32, 32, 3)


def test_shape_runs_lower_the_loss_and_measure_the_surface():
    from render.inverse.reconstruction import dented_blob, run_shape
    from render.inverse.shape import icosphere, surface_distances

    blob = dented_blob(2)
    start = run_shape(blob, views=2, size=24, iters=0, start_subdivisions=1, held_out=1,
                      samples=2000)  # fmt: skip
    expected = surface_distances(*icosphere(1), *blob, samples=2000)
    assert start["chamfer_percent"] == expected.chamfer
    assert start["hausdorff_percent"] == expected.hausdorff
    for method in ("large_steps", "laplacian"):
        run = run_shape(blob, views=2, size=24, iters=6, method=method, start_subdivisions=1,
                        held_out=1, antialias=True, lr=0.05, samples=500)  # fmt: skip
        assert run["final_loss"] < 0.9 * run["initial_loss"], method
    with pytest.raises(ValueError, match="method must be"):
        run_shape(blob, method="smooth")


def test_joint_run_lowers_the_loss_and_reports_every_parameter():
    from render.inverse.reconstruction import run_joint

    run = run_joint(views=2, size=16, iters=5, antialias=True, samples=1000)
    assert run["final_loss"] < run["initial_loss"]
    for key in ("camera_position_error_percent", "light_position_error_percent",
                "intensity_error_percent", "albedo_error_percent",
                "albedo_times_intensity_error_percent", "shape_chamfer_percent"):  # fmt: skip
        assert np.isfinite(run[key]) and run[key] >= 0, key
    assert run["shape_chamfer_at_start_percent"] > 0  # the bumps are there to recover
