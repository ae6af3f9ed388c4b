"""Vehicle body shapes: every type's mesh fills its data-sheet box (mirrors and roof box aside), is closed and
outward-facing, stands on its wheels, is rounded and hollowed where real bodies are, and gives a smaller
image box than its cuboid from roadside-camera views. Projections use OpenCV (sim.lens), never shapes.py."""

from __future__ import annotations

import math
from collections import Counter

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from schemas.common import CameraIntrinsics, VehicleProfile
from sim.errors import SimulationError
from sim.geometry import FloatArray, mount_rotation
from sim.lens import Lens
from sim.shapes import (
    CAR_TYPE_SHARES,
    TYPE_RANGES,
    VEHICLE_TYPES,
    BodyShape,
    body_type_for_class,
    cuboid_body,
    cuboid_points,
    draw_body,
)

CARS = ("sedan", "hatchback", "estate", "suv", "pickup")
SOLIDS = ("body", "cab", "box", "bed")  # the vehicle's body parts, as against wheels, mirrors, roof box
SEEDS = range(25)
EXACT = 1e-9  # float rounding of a mesh built from the data-sheet numbers


def _part(shape: BodyShape, prefix: str) -> FloatArray:
    chunks = [shape.vertices[s:e] for name, (s, e) in shape.parts.items() if name.startswith(prefix)]
    return np.concatenate(chunks) if chunks else np.zeros((0, 3))


def _solid(shape: BodyShape) -> FloatArray:
    return np.concatenate([_part(shape, name) for name in SOLIDS])


def _faces_of(shape: BodyShape, name: str) -> np.ndarray:
    start, stop = shape.parts[name]
    inside = np.all((shape.faces >= start) & (shape.faces < stop), axis=1)
    return shape.faces[inside]


def _signed_volume(vertices: FloatArray, faces: np.ndarray) -> float:
    a, b, c = vertices[faces[:, 0]], vertices[faces[:, 1]], vertices[faces[:, 2]]
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)


# Drawn once: the bodies are immutable and every per-type test reads the same ones.
BODIES = {t: [draw_body(t, np.random.default_rng(seed)) for seed in SEEDS] for t in VEHICLE_TYPES}


def _bodies(vehicle_type: str) -> list[BodyShape]:
    return BODIES[vehicle_type]


@pytest.mark.parametrize("vehicle_type", VEHICLE_TYPES)
def test_body_fills_its_data_sheet_box_and_only_mirrors_and_roof_box_leave_it(vehicle_type: str) -> None:
    for shape in _bodies(vehicle_type):
        L, W, H, p = shape.length_m, shape.width_m, shape.height_m, shape.proportions
        inside = np.concatenate([_solid(shape), _part(shape, "wheel")])
        assert np.all(inside >= -EXACT) and np.all(inside <= np.array([L, W, H]) + EXACT)
        # The data sheet's L, W and H are the body's own extremes (the box is tight).
        solid = _solid(shape)
        np.testing.assert_allclose(solid.min(axis=0)[:2], [0.0, 0.0], atol=EXACT)
        np.testing.assert_allclose(solid.max(axis=0), [L, W, H], atol=EXACT)
        mirrors = _part(shape, "mirror")
        out = p["mirror_out_m"]
        assert np.all(mirrors[:, 0] >= 0.0) and np.all(mirrors[:, 0] <= L) and np.all(mirrors[:, 2] <= H)
        np.testing.assert_allclose([mirrors[:, 1].min(), mirrors[:, 1].max()], [-out, W + out], atol=EXACT)
        everything = shape.vertices
        assert np.all(everything[:, 0] >= 0.0) and np.all(everything[:, 0] <= L)
        roof_box = _part(shape, "roof_box")
        assert (len(roof_box) > 0) == (p["roof_box"] == 1.0)
        if len(roof_box):
            assert roof_box[:, 2].min() > H and roof_box[:, 2].max() == pytest.approx(
                H + p["roof_box_height_m"]
            )
            assert np.all(roof_box[:, 1] > 0.0) and np.all(roof_box[:, 1] < W)


@pytest.mark.parametrize("vehicle_type", VEHICLE_TYPES)
def test_wheels_stand_on_the_road_inside_the_footprint_and_the_sill_at_ground_clearance(
    vehicle_type: str,
) -> None:
    for shape in _bodies(vehicle_type):
        L, W, p = shape.length_m, shape.width_m, shape.proportions
        contacts = shape.wheel_contacts
        assert contacts.shape == (4, 3) and np.all(contacts[:, 2] == 0.0)
        # rear-right, front-right, front-left, rear-left
        assert contacts[0, 0] == contacts[3, 0] < contacts[1, 0] == contacts[2, 0]
        assert contacts[0, 1] < W / 2 < contacts[3, 1] and contacts[1, 1] < W / 2 < contacts[2, 1]
        min_overhang = 0.5 if shape.vehicle_type in (*CARS, "van") else 1.0
        assert contacts[:, 0].min() > min_overhang and contacts[:, 0].max() < L - min_overhang
        for name in ("wheel_rr", "wheel_fr", "wheel_fl", "wheel_rl"):
            assert _part(shape, name)[:, 2].min() == 0.0
        assert _solid(shape)[:, 2].min() == pytest.approx(p["clearance_m"], abs=EXACT)
        assert 0.10 <= p["clearance_m"] <= 0.45


@pytest.mark.parametrize("vehicle_type", VEHICLE_TYPES)
def test_every_part_is_a_closed_outward_facing_surface(vehicle_type: str) -> None:
    for shape in _bodies(vehicle_type):
        assert shape.faces.min() == 0 and shape.faces.max() == len(shape.vertices) - 1
        covered = 0
        for name in shape.parts:
            faces = _faces_of(shape, name)
            covered += len(faces)
            directed = Counter(
                (int(a), int(b)) for f in faces for a, b in ((f[0], f[1]), (f[1], f[2]), (f[2], f[0]))
            )
            # Each edge once in each direction: closed, and consistently oriented.
            assert all(n == 1 for n in directed.values()), name
            assert all((b, a) in directed for a, b in directed), name
            assert _signed_volume(shape.vertices, faces) > 0.0, name
        assert covered == len(shape.faces)
        assert 100 <= len(shape.vertices) <= 260


@pytest.mark.parametrize("vehicle_type", VEHICLE_TYPES)
def test_bodies_are_clearly_smaller_than_their_box_and_rounded_at_the_corners(vehicle_type: str) -> None:
    ratios = []
    for shape in _bodies(vehicle_type):
        L, W, H = shape.length_m, shape.width_m, shape.height_m
        volume = sum(_signed_volume(shape.vertices, _faces_of(shape, n)) for n in SOLIDS if n in shape.parts)
        ratios.append(volume / (L * W * H))
        # No body vertex near a plan corner of the footprint (rounded corners, at every height).
        solid = _solid(shape)
        for corner in ((0.0, 0.0), (L, 0.0), (L, W), (0.0, W)):
            assert np.min(np.hypot(*(solid[:, :2] - corner).T)) > 0.005, corner  # box bodies: r >= 2 cm
    ratios_arr = np.array(ratios)
    lo, hi = {"truck": (0.45, 0.85), "bus": (0.75, 0.95), "van": (0.60, 0.85), "pickup": (0.35, 0.60)}.get(
        vehicle_type, (0.50, 0.75)
    )
    assert lo < ratios_arr.min() and ratios_arr.max() < hi, (
        f"volume / LWH {ratios_arr.min():.3f}-{ratios_arr.max():.3f}"
    )


def test_car_plan_corners_are_cut_by_their_radius() -> None:
    for vehicle_type in ("sedan", "hatchback", "estate", "suv"):
        for shape in _bodies(vehicle_type):
            solid = _solid(shape)
            L, W = shape.length_m, shape.width_m
            for corner in ((0.0, 0.0), (L, 0.0), (L, W), (0.0, W)):
                # A rounded corner of radius >= 0.3 m leaves >= 0.3 (sqrt 2 - 1) = 0.12 m of the diagonal.
                assert np.min(np.hypot(*(solid[:, :2] - corner).T)) > 0.10


LENS = Lens.from_intrinsics(
    CameraIntrinsics(
        width=1920, height=1080, fx=1000.0, fy=1000.0, cx=960.0, cy=540.0, dist=(-0.12, 0.03, 0, 0, 0)
    )
)
PINHOLE = Lens.from_intrinsics(
    CameraIntrinsics(width=1920, height=1080, fx=1000.0, fy=1000.0, cx=960.0, cy=540.0)
)


def _image_box(
    lens: Lens, points: FloatArray, yaw: float, distance: float, height: float, azimuth: float
) -> FloatArray:
    """Box [u1, v1, u2, v2] of vehicle-frame points of a vehicle whose footprint centre sits at the local
    origin heading `yaw`, seen by a camera `height` m up and `distance` m away at `azimuth`, aimed at it."""
    cos, sin = math.cos(yaw), math.sin(yaw)
    R_local_from_vehicle = np.array([[cos, -sin, 0.0], [sin, cos, 0.0], [0.0, 0.0, 1.0]])
    centre = np.array([points[:, 0].max() / 2.0, 0.0, 0.0])
    camera = np.array([distance * math.cos(azimuth), distance * math.sin(azimuth), height])
    R_cam_from_local = mount_rotation(azimuth + math.pi, math.atan2(height - 1.0, distance))
    local = (points - centre) @ R_local_from_vehicle.T
    pixels, ok = lens.project_cam((local - camera) @ R_cam_from_local.T)
    assert ok.all()
    return np.concatenate([pixels.min(axis=0), pixels.max(axis=0)])


def _area(box: FloatArray) -> float:
    return float((box[2] - box[0]) * (box[3] - box[1]))


views = dict(
    seed=st.integers(0, 2**31),
    yaw=st.floats(-math.pi, math.pi),
    distance=st.floats(20.0, 60.0),
    height=st.floats(8.0, 12.0),
    azimuth=st.floats(-math.pi, math.pi),
)


@settings(max_examples=100, deadline=None, derandomize=True, database=None)
@given(vehicle_type=st.sampled_from(CARS), **views)
def test_a_cars_box_from_a_roadside_view_is_smaller_than_its_cuboids(
    vehicle_type: str, seed: int, yaw: float, distance: float, height: float, azimuth: float
) -> None:
    shape = draw_body(vehicle_type, np.random.default_rng(seed))
    # Centre the cuboid on the same footprint (its x extent is the shape's data-sheet L as well).
    cuboid = cuboid_body(shape.length_m, shape.width_m, shape.height_m)
    points = shape.vertices - [0.0, shape.width_m / 2.0, 0.0]
    corners = cuboid.vertices - [0.0, shape.width_m / 2.0, 0.0]
    shape_box = _image_box(LENS, points, yaw, distance, height, azimuth)
    cuboid_box = _image_box(LENS, corners, yaw, distance, height, azimuth)
    ratio = _area(shape_box) / _area(cuboid_box)
    # Seen head-on the mirrors widen the box by up to 2 mirror_out / W while the height hardly shrinks, so
    # one view's box can exceed the cuboid's (as a real car's does); a roof box can add up to its height.
    p = shape.proportions
    bound = 1.0 + 2.0 * p["mirror_out_m"] / shape.width_m
    if p["roof_box"] == 1.0:
        bound *= 1.0 + p["roof_box_height_m"] / shape.height_m
    assert 0.5 < ratio < bound, f"{vehicle_type}: box area ratio {ratio:.3f}"


@pytest.mark.parametrize("vehicle_type", VEHICLE_TYPES)
def test_over_roadside_views_boxes_are_clearly_smaller_than_the_cuboids(vehicle_type: str) -> None:
    rng = np.random.default_rng(2026)
    ratios = []
    for _ in range(100):
        shape = draw_body(vehicle_type, rng)
        yaw, azimuth = rng.uniform(-math.pi, math.pi, size=2)
        view = (float(yaw), float(rng.uniform(20.0, 60.0)), float(rng.uniform(8.0, 12.0)), float(azimuth))
        centred = shape.vertices - [0.0, shape.width_m / 2.0, 0.0]
        corners = cuboid_body(shape.length_m, shape.width_m, shape.height_m).vertices - [
            0.0,
            shape.width_m / 2.0,
            0.0,
        ]
        ratios.append(_area(_image_box(LENS, centred, *view)) / _area(_image_box(LENS, corners, *view)))
    ratio = np.array(ratios)
    p5, p95 = np.percentile(ratio, [5.0, 95.0])
    summary = f"{vehicle_type}: box area ratio mean {ratio.mean():.3f}, 5-95 % {p5:.3f}-{p95:.3f}"
    # Cars lose their boot/bonnet corners, roof edges and bumper bottoms; box bodies (truck, bus) far less,
    # and their 0.2-0.35 m mirrors make head-on boxes wider than the cuboid's.
    mean_max, p95_max = (0.95, 1.10) if vehicle_type in ("truck", "bus") else (0.90, 1.0)
    assert 0.6 < ratio.mean() < mean_max and p95 < p95_max, summary


@settings(max_examples=100, deadline=None, derandomize=True, database=None)
@given(vehicle_type=st.sampled_from(VEHICLE_TYPES), **views)
def test_the_body_without_mirrors_and_roof_box_images_inside_its_cuboids_box(
    vehicle_type: str, seed: int, yaw: float, distance: float, height: float, azimuth: float
) -> None:
    # Through a pinhole the image of the box is the hull of its corners: anything inside projects inside.
    shape = draw_body(vehicle_type, np.random.default_rng(seed))
    solid = np.concatenate([_solid(shape), _part(shape, "wheel")]) - [0.0, shape.width_m / 2.0, 0.0]
    corners = cuboid_body(shape.length_m, shape.width_m, shape.height_m).vertices - [
        0.0,
        shape.width_m / 2.0,
        0.0,
    ]
    inner = _image_box(PINHOLE, solid, yaw, distance, height, azimuth)
    outer = _image_box(PINHOLE, corners, yaw, distance, height, azimuth)
    assert np.all(inner[:2] >= outer[:2] - 1e-6) and np.all(inner[2:] <= outer[2:] + 1e-6)
    assert _area(inner) < _area(outer)


@pytest.mark.parametrize("vehicle_type", VEHICLE_TYPES)
def test_given_data_sheet_dimensions_are_kept_exactly_and_seeds_repeat(vehicle_type: str) -> None:
    (l_lo, l_hi), (w_lo, w_hi), (h_lo, h_hi) = (
        TYPE_RANGES[vehicle_type][k] for k in ("length_m", "width_m", "height_m")
    )
    # The range's ends and beyond them (within the tolerance): the rest of the body must still fit.
    for L, W, H in (
        (l_lo, w_lo, h_lo),
        (l_hi, w_hi, h_hi),
        (0.85 * l_lo, 0.9 * w_lo, 0.85 * h_lo),
        (1.15 * l_hi, w_hi, 1.15 * h_hi),
    ):
        for seed in range(5):
            shape = draw_body(vehicle_type, np.random.default_rng(seed), length_m=L, width_m=W, height_m=H)
            assert (shape.length_m, shape.width_m, shape.height_m) == (L, W, H)
            p = shape.proportions
            assert (p["length_m"], p["width_m"], p["height_m"]) == (L, W, H)
            solid = _solid(shape)
            np.testing.assert_allclose(solid.max(axis=0), [L, W, H], atol=EXACT)
            assert np.all(solid >= -EXACT)
            assert shape.wheel_contacts[:, 0].min() > 0.3 and shape.wheel_contacts[:, 0].max() < L - 0.3
            assert p["roof_length_m"] > 0.3
    a = draw_body(vehicle_type, np.random.default_rng(11))
    b = draw_body(vehicle_type, np.random.default_rng(11))
    c = draw_body(vehicle_type, np.random.default_rng(12))
    assert a.proportions == b.proportions and np.array_equal(a.vertices, b.vertices)
    assert np.array_equal(a.faces, b.faces) and np.array_equal(a.wheel_contacts, b.wheel_contacts)
    assert a.proportions != c.proportions


def test_proportions_are_json_numbers_and_within_their_ranges() -> None:
    for shape in (body for t in VEHICLE_TYPES for body in _bodies(t)):
        assert all(isinstance(v, float) and math.isfinite(v) for v in shape.proportions.values())
        for name, (lo, hi) in TYPE_RANGES[shape.vehicle_type].items():
            # Clamps only ever lower a height or steepen a rake to keep the body consistent.
            assert shape.proportions[name] <= hi + EXACT, name
            if name in ("length_m", "width_m", "height_m", "wheel_radius_m", "mirror_out_m", "cab_length_m"):
                assert shape.proportions[name] >= lo, name


def test_roof_boxes_come_on_about_one_car_in_twenty() -> None:
    rng = np.random.default_rng(3)
    count = sum(draw_body("hatchback", rng).proportions["roof_box"] == 1.0 for _ in range(400))
    assert 8 <= count <= 33  # binomial(400, 0.05): mean 20, sd 4.4
    assert all(draw_body("van", rng).proportions["roof_box"] == 0.0 for _ in range(50))


def test_bad_input_is_refused_naming_the_field() -> None:
    rng = np.random.default_rng(0)
    with pytest.raises(SimulationError, match="vehicle_type: 'tank'"):
        draw_body("tank", rng)
    with pytest.raises(SimulationError, match=r"height_m: 3\.0 impossible for a sedan"):
        draw_body("sedan", rng, height_m=3.0)
    with pytest.raises(SimulationError, match="length_m: nan"):
        draw_body("bus", rng, length_m=float("nan"))
    with pytest.raises(SimulationError, match="width_m"):
        draw_body("truck", rng, width_m=1.0)
    with pytest.raises(SimulationError, match="cls: 3"):
        body_type_for_class(3, rng)
    with pytest.raises(SimulationError, match="height_m"):
        cuboid_body(4.0, 1.8, 0.0)


def test_toolbox_classes_map_to_body_types_with_car_shares() -> None:
    rng = np.random.default_rng(5)
    assert [body_type_for_class(c, rng) for c in (5, 6, 7)] == ["truck", "van", "bus"]
    counts = Counter(body_type_for_class(4, rng) for _ in range(4000))
    assert set(counts) == set(CAR_TYPE_SHARES)
    for name, share in CAR_TYPE_SHARES.items():
        assert abs(counts[name] / 4000 - share) < 4.0 * math.sqrt(share * (1 - share) / 4000), name
    # Given a data sheet, only the types that can have it: a 3.9 m car is no pickup, a 1.85 m tall no sedan.
    small = Counter(
        body_type_for_class(4, rng, length_m=3.9, width_m=1.75, height_m=1.45) for _ in range(300)
    )
    assert set(small) == {"sedan", "hatchback", "estate", "suv"}
    tall = Counter(body_type_for_class(4, rng, length_m=4.6, height_m=1.85) for _ in range(300))
    assert set(tall) == {"suv", "pickup"}
    for cls in (4, 5, 6, 7):
        vehicle_type = body_type_for_class(cls, rng, length_m=4.5)
        assert vehicle_type == {5: "truck", 6: "van", 7: "bus"}.get(cls, vehicle_type)
    with pytest.raises(SimulationError, match=r"cls: 4 \(car\): no car body type admits length_m = 9\.0"):
        body_type_for_class(4, rng, length_m=9.0)


def test_the_ideal_body_is_the_data_sheet_box() -> None:
    profile = VehicleProfile(length=4.8, width=1.85, height=1.5, imu_offset=(1.3, 0.925, 0.35))
    shape = cuboid_body(4.8, 1.85, 1.5)
    assert shape.vertices.shape == (8, 3) and shape.faces.shape == (12, 3)
    np.testing.assert_array_equal(shape.vertices, cuboid_points(profile))
    np.testing.assert_array_equal(shape.wheel_contacts, cuboid_points(profile)[:4])
    assert _signed_volume(shape.vertices, shape.faces) == pytest.approx(4.8 * 1.85 * 1.5, rel=1e-12)
    directed = Counter(
        (int(a), int(b)) for f in shape.faces for a, b in ((f[0], f[1]), (f[1], f[2]), (f[2], f[0]))
    )
    assert len(directed) == 36 and all((b, a) in directed for a, b in directed)
