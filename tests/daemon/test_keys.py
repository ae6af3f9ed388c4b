"""daemon.keys: every bus key as docs/design.md lists it, and the parsers that take them apart again."""

from __future__ import annotations

import pytest

from daemon import keys


def test_keys_are_the_documented_ones() -> None:
    assert keys.detections_key("r1", "c1") == "rsu/r1/camera/c1/detections"
    assert keys.image_key("r1", "c1") == "rsu/r1/camera/c1/image"
    assert keys.v2x_key(4242) == "v2x/cam/4242" and keys.ALL_V2X == "v2x/cam/*"
    assert keys.calibration_key("r1", "*") == "rsu/r1/camera/*/calibration"
    assert keys.status_key("r1", "c1") == "rsu/r1/camera/c1/calibration/status"
    assert keys.trigger_key("r1", "c1") == "rsu/r1/camera/c1/calibration/trigger"
    assert keys.transform_key("r1", "c1") == "rsu/r1/camera/c1/calibration/transform"
    assert keys.health_key("r1") == "rsu/r1/health" and keys.alive_key("r1") == "rsu/r1/alive"
    assert keys.location_topic(7) == "v2x/cam/7/location"
    assert keys.annotations_topic("r1", "c1") == "rsu/r1/camera/c1/detections/annotations"
    assert keys.origin_topic("r1", "c1") == "rsu/r1/camera/c1/calibration/origin"
    assert keys.camera_info_topic("r1", "c1") == "rsu/r1/camera/c1/calibration/camera_info"


def test_parsers_invert_the_builders() -> None:
    assert keys.parse_detections_key(keys.detections_key("r1", "c.1")) == ("r1", "c.1")
    assert keys.parse_image_key(keys.image_key("r-2", "c_1")) == ("r-2", "c_1")
    assert keys.parse_v2x_key(keys.v2x_key(4242)) == "4242"
    assert keys.parse_alive_key(keys.alive_key("r1")) == "r1"


@pytest.mark.parametrize(
    "key",
    [
        "",
        "rsu/r1/camera/c1",
        "rsu/r1/camera/c1/image",
        "rsu//camera/c1/detections",
        "rsu/r1/camera//detections",
        "rsu/r1/camera/c1/detections/annotations",
        "rsu/r1/cam/c1/detections",
        "v2x/cam/7",
    ],
)
def test_other_keys_are_no_detections_key(key: str) -> None:
    assert keys.parse_detections_key(key) is None


@pytest.mark.parametrize("key", ["v2x/cam", "v2x/cam/", "v2x/cam/7/location", "v2x/denm/7", "rsu/r1/alive"])
def test_other_keys_are_no_v2x_key(key: str) -> None:
    assert keys.parse_v2x_key(key) is None


@pytest.mark.parametrize("key", ["rsu/r1", "rsu//alive", "rsu/r1/health", "rsu/r1/alive/x", "v2x/r1/alive"])
def test_other_keys_are_no_alive_key(key: str) -> None:
    assert keys.parse_alive_key(key) is None
