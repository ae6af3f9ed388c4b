"""bench.bound: its linear algebra, and that its noise models are the simulator's."""

from __future__ import annotations

import math

import numpy as np
import pytest

from bench.bound import (
    _bound,
    _Camera,
    _View,
    camera_bounds,
    edge_noise_covariance,
    gauss_markov_covariance,
    posterior_covariance,
    roll_columns,
    time_column,
)
from pipeline.vehicle_model import largest_stds
from sim.v2x import GnssSpec


def _problem(rng: np.random.Generator) -> tuple[np.ndarray, ...]:
    J = rng.normal(size=(40, 3))
    G = rng.normal(size=(40, 2))
    A = rng.normal(size=(40, 40))
    noise = A @ A.T / 40.0 + 0.1 * np.eye(40)
    prior = np.diag([0.5, 2.0])
    return J, G, noise, prior


def test_integrating_out_a_nuisance_equals_estimating_it_with_its_prior():
    J, G, noise, prior = _problem(np.random.default_rng(0))
    # Joint information of [x, n] with n's prior; x's block of its inverse.
    N_inv = np.linalg.inv(noise)
    joint = np.block(
        [[J.T @ N_inv @ J, J.T @ N_inv @ G], [G.T @ N_inv @ J, G.T @ N_inv @ G + np.linalg.inv(prior)]]
    )
    expected = np.linalg.inv(joint)[:3, :3]
    np.testing.assert_allclose(posterior_covariance(J, noise, G, prior), expected, rtol=1e-9, atol=1e-12)
    # A nuisance only adds uncertainty.
    without = posterior_covariance(J, noise)
    assert np.all(np.linalg.eigvalsh(posterior_covariance(J, noise, G, prior) - without) > -1e-12)
    assert np.trace(posterior_covariance(J, noise, G, prior)) > 1.01 * np.trace(without)


def test_the_bound_is_the_scatter_of_the_best_linear_estimate():
    rng = np.random.default_rng(1)
    J, G, noise, prior = _problem(rng)
    total = noise + G @ prior @ G.T
    W = np.linalg.inv(total)
    gain = np.linalg.inv(J.T @ W @ J) @ J.T @ W
    draws = 20_000
    e = rng.multivariate_normal(np.zeros(40), noise, size=draws)
    n = rng.multivariate_normal(np.zeros(2), prior, size=draws)
    x = np.array([0.3, -1.0, 2.0])
    estimates = (J @ x + n @ G.T + e) @ gain.T
    np.testing.assert_allclose(estimates.mean(axis=0), x, atol=0.02)
    bound = posterior_covariance(J, noise, G, prior)
    np.testing.assert_allclose(np.cov(estimates.T), bound, rtol=0.05, atol=0.02 * np.abs(bound).max())


def test_largest_stds_takes_the_worst_direction_of_each_block():
    # The gates' measure, which the bound's "passable" uses (pipeline.vehicle_model.largest_stds).
    covariance = np.zeros((6, 6))
    covariance[:3, :3] = np.diag([1e-6, 4e-6, 1e-6])
    covariance[3:, 3:] = [[0.01, 0.0, 0.0], [0.0, 0.02, 0.015], [0.0, 0.015, 0.02]]
    position, rotation = largest_stds(covariance)
    assert position == pytest.approx(math.sqrt(0.035))
    assert rotation == pytest.approx(math.degrees(2e-3))


def test_gnss_covariance_is_the_simulators_bias_and_wander():
    from sim.v2x import GnssSpec, gauss_markov

    spec = GnssSpec.rtk_fixed()
    rng = np.random.default_rng(2)
    t_s = np.sort(rng.uniform(0.0, 200.0, 6))
    draws = 20_000
    samples = np.array(
        [
            rng.normal(0.0, spec.bias_sigma_m)
            + gauss_markov(t_s, spec.wander_sigma_m, spec.wander_tau_s, 1, rng)[:, 0]
            for _ in range(draws)
        ]
    )
    expected = gauss_markov_covariance(t_s, spec.bias_sigma_m, spec.wander_sigma_m, spec.wander_tau_s)
    np.testing.assert_allclose(np.cov(samples.T), expected, atol=4e-5)


def test_edge_noise_covariance_is_the_simulators_detector_noise():
    from sim.detector import _correlate_along_tracks, _edge_noise
    from sim.lens import Lens
    from sim.presets import REAL_DETECTOR_FLOOR

    spec = REAL_DETECTOR_FLOOR
    lens = Lens(np.eye(3), np.zeros(5), 1920, 1080, math.inf)
    boxes = np.array(
        [[100, 100, 140, 130], [110, 100, 260, 220], [300, 300, 330, 320], [500, 400, 700, 600]], float
    )
    frames = np.array([0, 1, 3, 0])
    owner = np.array([0, 0, 0, 1])
    draws = 20_000
    rng = np.random.default_rng(3)
    samples = np.empty((draws, 16))
    for k in range(draws):
        z = rng.standard_normal((4, 4)) * spec.box_jitter_px
        correlated = _correlate_along_tracks(z, owner, frames, spec.jitter_ar1)
        samples[k] = _edge_noise(boxes, correlated, spec, lens).reshape(-1)
    expected = edge_noise_covariance(
        boxes, frames, owner, spec.box_jitter_px, spec.jitter_reference_px, spec.jitter_ar1
    )
    np.testing.assert_allclose(np.cov(samples.T), expected, atol=0.06 * expected.max())
    # Different tracks and edges do not correlate; the same edge of a track does, by rho ** gap.
    assert expected[0, 12] == 0.0 and expected[0, 1] == 0.0
    assert expected[0, 8] == pytest.approx(math.sqrt(expected[0, 0] * expected[8, 8]) * spec.jitter_ar1**3)


def test_every_unknown_handed_back_raises_the_bound():
    from sim.simulate import simulate

    sim = simulate("sil-north", 0)
    known = camera_bounds(sim, "known", "exact")
    unknown = camera_bounds(sim, "prior", "family")
    assert [r["camera"] for r in known] == [r["camera"] for r in unknown] == ["north"]
    a, b = known[0], unknown[0]
    assert a["frames"] == b["frames"] >= 50 and a["traversals"] == 3
    # The detector alone fixes the pose to centimetres; the GNSS's bias and wander (4 cm and 6 cm
    # vertically) set a floor on the camera's height no number of boxes removes.
    assert float(a["detector_only_position_std_m"]) < 0.5 * float(a["position_std_m"])
    assert 0.04 < float(a["height_std_m"]) < 0.12
    assert float(b["position_std_m"]) >= float(a["position_std_m"])
    assert float(b["rotation_std_deg"]) > float(a["rotation_std_deg"])
    # The clock estimated with the pose: the pose's bound rises (or holds), the clock's own is milliseconds.
    clocked = camera_bounds(sim, "known", "exact", "unknown")[0]
    assert a["time_offset_std_ms"] is None
    assert 0.1 < float(clocked["time_offset_std_ms"]) < 10.0
    assert float(clocked["position_std_m"]) >= float(a["position_std_m"]) - 1e-9
    # Each further unknown raises the rotation's bound: the edge offsets, then the scale; the vehicle's roll.
    offsets = camera_bounds(sim, "offsets", "exact")[0]
    scaled = camera_bounds(sim, "prior", "exact")[0]
    rolled = camera_bounds(sim, "known", "exact", roll_std_deg=0.5)[0]
    assert (
        float(a["rotation_std_deg"]) < float(offsets["rotation_std_deg"]) <= float(scaled["rotation_std_deg"])
    )
    assert float(rolled["rotation_std_deg"]) > float(a["rotation_std_deg"])


def _across_road_view(poses: np.ndarray, side: float, distance_m: float) -> _View:
    """A 4.5 x 1.8 x 1.5 m box at the poses (n, 6), seen by a camera 6 m up, distance_m from the road's
    centre on the side `side` (-1: y < 0, looking along +y; +1: looking along -y), tilted down by 15 deg,
    through a 1920 x 1080 lens of f = 1000 px."""
    from sim.geometry import attitude_matrices
    from sim.lens import Lens

    corners = np.array([[x, y, z] for x in (-2.25, 2.25) for y in (-0.9, 0.9) for z in (0.0, 1.5)])
    R = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])  # camera z along local +y
    if side > 0:
        R = R @ np.diag([-1.0, -1.0, 1.0])
    tilt = math.radians(15.0)
    R = np.array([[1, 0, 0], [0, math.cos(tilt), -math.sin(tilt)], [0, math.sin(tilt), math.cos(tilt)]]) @ R
    lens = Lens(np.array([[1000.0, 0, 960], [0, 1000.0, 540], [0, 0, 1]]), np.zeros(5), 1920, 1080, math.inf)
    attitude = attitude_matrices(poses[:, 3], poses[:, 4], poses[:, 5])
    return _View(attitude, poses[:, :3], corners, R, np.array([0.0, side * distance_m, 6.0]), lens)


def test_a_late_clock_moves_the_boxes_as_the_vehicle_moves():
    # The box driving along x at 12 m/s past a camera 20 m aside, looking across the road (+y).
    t_s = np.arange(30) * 0.1
    poses = np.zeros((30, 6))
    poses[:, 0] = -15.0 + 12.0 * t_s
    view = _across_road_view(poses, -1.0, 20.0)
    column = time_column(poses, t_s, np.zeros(30, dtype=np.int64), view)
    # The vehicle a little later is the camera a little earlier along -x: d box / dt = -12 d box / d C_x.
    expected = -12.0 * view.jacobian()[:, :, 3].reshape(-1)
    np.testing.assert_allclose(column, expected, rtol=1e-4, atol=1e-3)
    assert np.abs(column).max() > 100.0  # px/s: the test would see a column of zeros
    # A roll per drive-past moves only that drive-past's boxes.
    traversal = np.repeat([3, 7], 15)
    rolls = roll_columns(poses, traversal, view).reshape(30, 4, 2)
    assert np.all(rolls[15:, :, 0] == 0.0) and np.all(rolls[:15, :, 1] == 0.0)
    assert np.abs(rolls[:15, :, 0]).max() > 1.0 and np.abs(rolls[15:, :, 1]).max() > 1.0  # px/rad


def _drive_past_camera(name: str, side: float, distance_m: float, t0_s: float) -> _Camera:
    """The camera of _across_road_view seeing the box drive past twice at 12 m/s from t0_s (scene clock):
    along +x in the lane at y = -1.75 m, then 20 s later back along -x at y = +1.75 m. Its edge noise
    white, 1 px."""
    n = 30
    runs = []
    for traversal, (lane_y, direction, start_s) in enumerate(((-1.75, 1.0, 0.0), (1.75, -1.0, 20.0))):
        pose = np.zeros((n, 6))
        pose[:, 0] = direction * (-15.0 + 12.0 * np.arange(n) * 0.1)
        pose[:, 1] = lane_y
        pose[:, 3] = 0.0 if direction > 0 else math.pi
        runs.append((pose, t0_s + start_s + np.arange(n) * 0.1, np.full(n, traversal)))
    poses = np.vstack([r[0] for r in runs])
    view = _across_road_view(poses, side, distance_m)
    J = view.jacobian()
    return _Camera(
        record={"camera": name},
        J=J.reshape(-1, 6),
        time=np.zeros(0),
        noise=np.eye(4 * len(poses)),
        gnss=-J[:, :, 3:6],
        t_s=np.concatenate([r[1] for r in runs]),
        traversal=np.concatenate([r[2] for r in runs]).astype(np.int64),
        own=None,
        body=None,
        roll=None,
        roll_variance=0.0,
        R=view.R,
    )


def test_cameras_bounded_together_share_the_vehicles_gnss_error():
    near, far = _drive_past_camera("near", -1.0, 15.0, 0.0), _drive_past_camera("far", 1.0, 25.0, 0.0)
    # No common bias: only the wander, 6 cm (12 cm vertically) over 60 s.
    wander = GnssSpec(bias_sigma_m=0.0, wander_sigma_m=0.06, wander_tau_s=60.0, vertical_factor=2.0)
    together = {r["camera"]: r for r in _bound([near, far], wander, "known")}
    assert together["near"]["joint_with"] == ["far"]
    for camera in (near, far):
        alone = _bound([camera], wander, "known")[0]
        assert alone["joint_with"] == []
        joint = together[str(camera.record["camera"])]
        # The other camera, across the road, sees the same two drive-pasts at the same instants: it
        # measures how far apart the vehicle's GNSS heights in the two lanes wandered, which turns a camera
        # as much as a roll would: the rotation's bound falls. Sharing can never raise a bound.
        assert float(joint["rotation_std_deg"]) < 0.9 * float(alone["rotation_std_deg"])
        assert float(joint["position_std_m"]) <= float(alone["position_std_m"]) * (1 + 1e-9)
    # Seen an hour apart (far beyond the wander's 60 s) the errors are independent: nothing shared.
    alone = _bound([near], wander, "known")[0]
    later = _drive_past_camera("far", 1.0, 25.0, 3600.0)
    apart = {r["camera"]: r for r in _bound([near, later], wander, "known")}
    for key in ("position_std_m", "rotation_std_deg", "height_std_m"):
        assert float(apart["near"][key]) == pytest.approx(float(alone[key]), rel=1e-6)
