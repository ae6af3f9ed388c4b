"""Foxglove views: every message decodes with Foxglove's official protobuf classes and says what it should."""

from __future__ import annotations

import math

import numpy as np
import pytest
from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.ImageAnnotations_pb2 import ImageAnnotations
from foxglove_schemas_protobuf.LocationFix_pb2 import LocationFix
from foxglove_schemas_protobuf.PointsAnnotation_pb2 import PointsAnnotation
from google.protobuf.descriptor_pb2 import FileDescriptorSet
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from daemon import foxglove
from schemas.common import CameraIntrinsics
from schemas.messages import V2xAccuracies, V2xPosition
from schemas.results import CalibrationResult, ReferenceFrame, Verdict

STAMP_NS = 1_717_200_000_123_456_789


def _v2x(**overrides: object) -> V2xPosition:
    fields: dict[str, object] = dict(
        station_id=4242, stamp_ns=STAMP_NS, lat=48.137, lon=11.575, alt=519.5, heading_deg=90.0, speed=12.0
    )
    fields.update(overrides)
    return V2xPosition.model_validate(fields)


def test_location_fix_decodes_with_the_official_class() -> None:
    fix = LocationFix.FromString(foxglove.location_fix(_v2x(), is_vehicle=True))
    assert (fix.latitude, fix.longitude, fix.altitude) == (48.137, 11.575, 519.5)
    assert fix.timestamp.ToNanoseconds() == STAMP_NS
    assert fix.frame_id == "v2x/4242"
    assert fix.position_covariance_type == LocationFix.UNKNOWN
    assert list(fix.position_covariance) == []
    assert (fix.color.r, fix.color.g, fix.color.b, fix.color.a) == pytest.approx(
        foxglove.VEHICLE_STATION_RGBA
    )
    other = LocationFix.FromString(foxglove.location_fix(_v2x(station_id=7), is_vehicle=False))
    assert other.frame_id == "v2x/7"
    assert (other.color.r, other.color.g, other.color.b) == pytest.approx(foxglove.OTHER_STATION_RGBA[:3])


def test_location_fix_carries_reported_accuracies_as_covariance() -> None:
    both = _v2x(accuracies=V2xAccuracies(horizontal_m=0.5, vertical_m=2.0))
    fix = LocationFix.FromString(foxglove.location_fix(both, is_vehicle=True))
    assert fix.position_covariance_type == LocationFix.DIAGONAL_KNOWN
    assert list(fix.position_covariance) == [0.25, 0, 0, 0, 0.25, 0, 0, 0, 4.0]
    horizontal = _v2x(accuracies=V2xAccuracies(horizontal_m=3.0))
    fix = LocationFix.FromString(foxglove.location_fix(horizontal, is_vehicle=True))
    assert fix.position_covariance_type == LocationFix.APPROXIMATED
    assert list(fix.position_covariance) == [9.0, 0, 0, 0, 9.0, 0, 0, 0, 9.0]


@settings(max_examples=60, deadline=None)
@given(
    stamp_ns=st.integers(0, 2**63 - 1),
    boxes=st.lists(
        st.tuples(st.floats(-1e5, 1e5), st.floats(-1e5, 1e5), st.floats(0.001, 1e3), st.floats(0.001, 1e3)),
        max_size=40,
    ),
    vehicle=st.lists(
        st.tuples(st.floats(0, 1e4), st.floats(0, 1e4), st.floats(1, 10), st.floats(1, 10)), max_size=2
    ),
)
def test_image_annotations_round_trip_every_box(
    stamp_ns: int,
    boxes: list[tuple[float, float, float, float]],
    vehicle: list[tuple[float, float, float, float]],
) -> None:
    dicts = [{"x1": x, "y1": y, "x2": x + w, "y2": y + h} for x, y, w, h in boxes]
    vehicle_boxes = [(x, y, x + w, y + h) for x, y, w, h in vehicle]
    decoded = ImageAnnotations.FromString(foxglove.image_annotations(stamp_ns, dicts, vehicle_boxes))
    assert decoded.timestamp.ToNanoseconds() == stamp_ns
    assert len(decoded.points) == len(dicts) + len(vehicle_boxes)
    expected = [(d["x1"], d["y1"], d["x2"], d["y2"], False) for d in dicts]
    expected += [(*box, True) for box in vehicle_boxes]
    for annotation, (x1, y1, x2, y2, is_vehicle) in zip(decoded.points, expected, strict=True):
        assert annotation.type == PointsAnnotation.LINE_LOOP
        assert annotation.timestamp.ToNanoseconds() == stamp_ns
        assert [(p.x, p.y) for p in annotation.points] == [(x1, y1), (x2, y1), (x2, y2), (x1, y2)]
        rgba = foxglove.VEHICLE_BOX_RGBA if is_vehicle else foxglove.BOX_RGBA
        color = annotation.outline_color
        assert (color.r, color.g, color.b, color.a) == pytest.approx(rgba)
        thickness = foxglove.VEHICLE_BOX_THICKNESS_PX if is_vehicle else foxglove.BOX_THICKNESS_PX
        assert annotation.thickness == thickness


def test_wire_encoding_equals_the_official_encoding_after_parsing() -> None:
    """Built with the official classes field by field, the same message serialises to the same bytes."""
    box = {"x1": 10.5, "y1": 20.25, "x2": 110.0, "y2": 220.0}
    official = ImageAnnotations()
    official.timestamp.FromNanoseconds(STAMP_NS)
    points = official.points.add()
    points.timestamp.FromNanoseconds(STAMP_NS)
    points.type = PointsAnnotation.LINE_LOOP
    for x, y in ((10.5, 20.25), (110.0, 20.25), (110.0, 220.0), (10.5, 220.0)):
        point = points.points.add()
        point.x, point.y = x, y
    points.outline_color.r, points.outline_color.g, points.outline_color.b, points.outline_color.a = (
        foxglove.BOX_RGBA
    )
    points.thickness = foxglove.BOX_THICKNESS_PX
    ours = ImageAnnotations.FromString(foxglove.image_annotations(STAMP_NS, [box]))
    assert ours == official
    assert ours.SerializeToString(deterministic=True) == official.SerializeToString(deterministic=True)


def test_timestamps_outside_protobuf_range_are_refused() -> None:
    with pytest.raises(ValueError, match="stamp_ns"):
        foxglove.image_annotations(-1, [])


def _result(R: np.ndarray, centre_local: np.ndarray, accepted: bool = True) -> CalibrationResult:
    t = -R @ centre_local
    return CalibrationResult(
        rsu_id="rsu-1",
        camera_id="cam-a",
        result_id="r1",
        created_at_ns=STAMP_NS,
        frame=ReferenceFrame(crs="EPSG:32632", origin=(690_000.0, 5_334_000.0, 500.0)),
        R=tuple(map(tuple, R.tolist())) if accepted else None,  # type: ignore[arg-type]
        t=tuple(t.tolist()) if accepted else None,  # type: ignore[arg-type]
        intrinsics=CameraIntrinsics(
            width=1920,
            height=1080,
            fx=1400.0,
            fy=1410.0,
            cx=960.5,
            cy=540.25,
            dist=(-0.1, 0.02, 0.001, 0.0, 0.0),
        ),
        verdict=Verdict(status="accepted" if accepted else "refused", reasons=[] if accepted else ["x"]),
    )


@settings(max_examples=40, deadline=None)
@given(quat=st.tuples(*[st.floats(-1, 1)] * 4).filter(lambda q: sum(c * c for c in q) > 0.01))
def test_frame_transform_places_the_camera_in_utm(quat: tuple[float, float, float, float]) -> None:
    R_world_from_cam = Rotation.from_quat(quat).as_matrix()  # scipy: x, y, z, w
    centre_local = np.array([12.0, -40.0, 8.5])
    result = _result(R_world_from_cam.T, centre_local)
    message = FrameTransform.FromString(foxglove.frame_transform(result))
    assert message.parent_frame_id == "EPSG:32632"
    assert message.child_frame_id == "rsu/rsu-1/camera/cam-a"
    assert message.timestamp.ToNanoseconds() == STAMP_NS
    centre = np.array([message.translation.x, message.translation.y, message.translation.z])
    np.testing.assert_allclose(centre, centre_local + np.array(result.frame.origin), atol=1e-6)
    q = message.rotation
    assert math.isclose(q.x**2 + q.y**2 + q.z**2 + q.w**2, 1.0, rel_tol=1e-9)
    R_decoded = Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix()
    np.testing.assert_allclose(R_decoded, R_world_from_cam, atol=1e-9)
    # A point in the camera frame maps to the world as the result's own R, t say.
    p_cam = np.array([0.3, -0.2, 25.0])
    p_local = np.asarray(result.R).T @ (p_cam - np.asarray(result.t))
    np.testing.assert_allclose(R_decoded @ p_cam + centre, p_local + np.array(result.frame.origin), atol=1e-6)


def test_origin_transform_and_camera_calibration() -> None:
    result = _result(np.eye(3), np.zeros(3))
    origin = FrameTransform.FromString(foxglove.origin_transform(result))
    assert (origin.parent_frame_id, origin.child_frame_id) == ("EPSG:32632", "rsu/rsu-1/camera/cam-a/local")
    assert (origin.translation.x, origin.translation.y, origin.translation.z) == result.frame.origin
    assert (origin.rotation.w, origin.rotation.x, origin.rotation.y, origin.rotation.z) == (
        1.0,
        0.0,
        0.0,
        0.0,
    )
    info = CameraCalibration.FromString(foxglove.camera_calibration(result))
    assert info.frame_id == "rsu/rsu-1/camera/cam-a"
    assert (info.width, info.height, info.distortion_model) == (1920, 1080, "plumb_bob")
    assert list(info.D) == pytest.approx([-0.1, 0.02, 0.001, 0.0, 0.0])
    assert list(info.K) == [1400.0, 0.0, 960.5, 0.0, 1410.0, 540.25, 0.0, 0.0, 1.0]
    assert list(info.P) == [1400.0, 0.0, 960.5, 0.0, 0.0, 1410.0, 540.25, 0.0, 0.0, 0.0, 1.0, 0.0]
    assert info.timestamp.ToNanoseconds() == STAMP_NS


RATIONAL = (2.1, 0.6, 4e-4, -3e-4, 0.01, 2.45, 1.3, 0.08)


@pytest.mark.parametrize(
    ("dist", "model", "D"),
    [
        ((-0.1, 0.02, 0.001, 0.002), "plumb_bob", [-0.1, 0.02, 0.001, 0.002, 0.0]),
        (RATIONAL, "rational_polynomial", list(RATIONAL)),
    ],
)
def test_camera_calibration_names_the_distortion_model(
    dist: tuple[float, ...], model: str, D: list[float]
) -> None:
    result = _result(np.eye(3), np.zeros(3))
    result = result.model_copy(update={"intrinsics": result.intrinsics.model_copy(update={"dist": dist})})
    info = CameraCalibration.FromString(foxglove.camera_calibration(result))
    assert info.distortion_model == model
    assert list(info.D) == pytest.approx(D)


def test_refused_result_has_no_transform() -> None:
    with pytest.raises(ValueError, match="no pose"):
        foxglove.frame_transform(_result(np.eye(3), np.zeros(3), accepted=False))


@pytest.mark.parametrize("name", ["LocationFix", "ImageAnnotations", "FrameTransform", "CameraCalibration"])
def test_schema_data_is_the_official_file_descriptor_set(name: str) -> None:
    schema = foxglove.protobuf_schema(name)
    assert (schema.name, schema.encoding, schema.message_encoding) == (
        f"foxglove.{name}",
        "protobuf",
        "protobuf",
    )
    files = FileDescriptorSet.FromString(schema.data)
    names = [file.name for file in files.file]
    assert names[-1] == f"foxglove/{name}.proto"
    assert len(names) == len(set(names))
    # Dependencies come before the files that import them (what MCAP readers build the pool from).
    for index, file in enumerate(files.file):
        assert set(file.dependency) <= set(names[:index])
