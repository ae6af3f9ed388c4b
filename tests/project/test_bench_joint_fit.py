"""bench.joint_fit: drive-pasts matched across cameras by time, and a joint fit that finds the heights the
vehicle's GNSS put each drive-past at, shared by the junction's two cameras."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from bench.joint_fit import CameraCase, _huber, drive_past_groups, fit_together
from bench.oracle_fit import oracle_inputs
from pipeline.association import Trajectory
from pipeline.camera import CameraModel, rotation_angle_rad
from pipeline.vehicle_model import ModelParams, cuboid_params, fit_trimmed
from sim.simulate import simulate

S = 1_000_000_000


def test_drive_pasts_seen_by_two_cameras_within_the_gap_are_one():
    first = np.array([[0, 10 * S], [100 * S, 110 * S], [300 * S, 305 * S]])
    second = np.array([[12 * S, 20 * S], [200 * S, 210 * S], [302 * S, 320 * S]])
    groups = drive_past_groups([first, second], gap_s=5.0)
    assert groups[0].tolist() == [0, 1, 3]
    assert groups[1].tolist() == [0, 2, 3]
    # 6 s apart is beyond a 5 s gap: separate drive-pasts
    apart = drive_past_groups([np.array([[0, 10 * S]]), np.array([[16 * S, 20 * S]])], gap_s=5.0)
    assert [g.tolist() for g in apart] == [[0], [1]]


@pytest.fixture(scope="module")
def raised_scene():
    """The first simulator's sil-west (cuboid boxes, true poses), each drive-past's heights moved by its own
    offset as a wandering GNSS would: the junction camera sees the vehicle turn, the arm camera looks along
    the road."""
    sim = simulate("sil-west", 0, ideal=True)
    ids = [camera.camera_id for camera in sim.cameras]
    inputs = {cid: oracle_inputs(sim, cid, 0, "true") for cid in ids}
    assert all(value is not None for value in inputs.values())
    latency = {cid: sim.ground_truth[cid].latency_ns for cid in ids}
    # The drive-pasts on the vehicle's clock, from the junction camera's tracks.
    tracks = inputs[ids[0]][0]  # type: ignore[index]
    spans = sorted((int(t.stamps[0]) - latency[ids[0]], int(t.stamps[-1]) - latency[ids[0]]) for t in tracks)
    cuts = [(a[1] + b[0]) // 2 for a, b in itertools.pairwise(spans)]
    offsets = np.array([0.09, -0.07, 0.02, -0.03, 0.05][: len(spans)])
    cases, truths = [], []
    params = cuboid_params(ModelParams())
    for cid, camera in zip(ids, sim.cameras, strict=True):
        own, trajectory = inputs[cid]  # type: ignore[misc]
        which = np.searchsorted(np.array(cuts), trajectory.stamps - latency[cid])
        poses = trajectory.poses.copy()
        poses[:, 2] += offsets[which]
        raised = Trajectory(trajectory.stamps, poses)
        R, t = camera.R_cam_from_local, camera.t_cam_from_local
        model = CameraModel.from_intrinsics(camera.intrinsics)
        start, used = fit_trimmed(R, t, own, raised, model, sim.vehicle, params)
        cases.append(CameraCase(cid, used, raised, model, latency[cid], start))
        truths.append((R, -R.T @ t))
    return sim, cases, truths, offsets, params


def test_the_joint_fit_finds_each_drive_past_height_and_both_poses(raised_scene):
    sim, cases, truths, offsets, params = raised_scene
    poses = fit_together(cases, sim.vehicle, params)
    for pose, _case, (R, C) in zip(poses, cases, truths, strict=True):
        found = pose.height_offsets_m
        assert len(found) == len(offsets)
        # The vehicle sat `found` above its reported heights, which were raised by `offsets`. The common part
        # trades with the cameras' heights (known to the prior only); the differences not.
        np.testing.assert_allclose(found - found.mean(), -(offsets - offsets.mean()), atol=0.01)
        assert np.linalg.norm(pose.camera_centre - C) < 0.05
        assert math.degrees(rotation_angle_rad(pose.R_cam_from_local, R)) < 0.05
    # The arm camera alone, its heights taken as reported, turns by the heights' differences.
    arm, (R, _) = cases[1], truths[1]
    assert math.degrees(rotation_angle_rad(arm.start.R_cam_from_local, R)) > 0.2


def test_each_rows_huber_bends_at_its_own_scale():
    f = np.array([0.5, 0.5, 2.0, 2.0, math.inf])
    z = np.array([0.04, 1.0, 1.0, 9.0, 100.0])  # r^2: inside, beyond, inside, beyond, a prior row
    rho, first, second = _huber(f)(z)
    # scipy's Huber at f_scale = f: f^2 rho(z / f^2), rho(u) = u inside 1, 2 sqrt(u) - 1 beyond
    u = z / f**2
    np.testing.assert_allclose(rho, np.where(u <= 1, z, f**2 * (2 * np.sqrt(u) - 1)))
    h = 1e-6
    np.testing.assert_allclose(first, (_huber(f)(z + h)[0] - _huber(f)(z - h)[0]) / (2 * h), rtol=1e-5)
    np.testing.assert_allclose(second, (_huber(f)(z + h)[1] - _huber(f)(z - h)[1]) / (2 * h), atol=1e-6)
