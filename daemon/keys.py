"""Every Zenoh key (and MCAP topic) rsucal uses, built and parsed in one place (docs/design.md, "Bus keys").

Builders take identifiers that schemas.common.Identifier already checked (safe in a key: no '/', '*',
'$'); passing "*" gives the wildcard a subscriber or a query uses. Parsers return the segments of a key of
their kind, or None for any other key (they never raise: keys come from outside).
"""

from __future__ import annotations

# ---------------------------------------------------------------------------------------------- inputs


def detections_key(rsu_id: str, camera_id: str) -> str:
    """A camera's detections (DetectionFrame JSON)."""
    return f"rsu/{rsu_id}/camera/{camera_id}/detections"


def image_key(rsu_id: str, camera_id: str) -> str:
    """A camera's images (foxglove.CompressedImage), for its detector."""
    return f"rsu/{rsu_id}/camera/{camera_id}/image"


def v2x_key(station_id: int | str) -> str:
    """A station's V2X positions (V2xPosition JSON)."""
    return f"v2x/cam/{station_id}"


ALL_V2X = v2x_key("*")  # every station's V2X positions


# ---------------------------------------------------------------------------------------------- outputs


def calibration_key(rsu_id: str, camera_id: str) -> str:
    """A camera's calibration: put when published, queryable (the current result)."""
    return f"rsu/{rsu_id}/camera/{camera_id}/calibration"


def status_key(rsu_id: str, camera_id: str) -> str:
    return f"{calibration_key(rsu_id, camera_id)}/status"


def trigger_key(rsu_id: str, camera_id: str) -> str:
    return f"{calibration_key(rsu_id, camera_id)}/trigger"


def transform_key(rsu_id: str, camera_id: str) -> str:
    """An accepted result as foxglove.FrameTransform (world -> camera), on the bus and in the recording."""
    return f"{calibration_key(rsu_id, camera_id)}/transform"


def health_key(rsu_id: str) -> str:
    return f"rsu/{rsu_id}/health"


def alive_key(rsu_id: str) -> str:
    return f"rsu/{rsu_id}/alive"


# ------------------------------------------------------------------------------------------ recorded only


def location_topic(station_id: int) -> str:
    """A station's foxglove.LocationFix, beside its raw v2x_key."""
    return f"{v2x_key(station_id)}/location"


def annotations_topic(rsu_id: str, camera_id: str) -> str:
    """A camera's foxglove.ImageAnnotations, beside its raw detections_key."""
    return f"{detections_key(rsu_id, camera_id)}/annotations"


def calibration_annotations_topic(rsu_id: str, camera_id: str) -> str:
    """The calibration vehicle's boxes as an accepted job identified them (foxglove.ImageAnnotations)."""
    return f"{calibration_key(rsu_id, camera_id)}/annotations"


def origin_topic(rsu_id: str, camera_id: str) -> str:
    """A result's local origin as foxglove.FrameTransform (world -> local frame)."""
    return f"{calibration_key(rsu_id, camera_id)}/origin"


def camera_info_topic(rsu_id: str, camera_id: str) -> str:
    """An accepted result's intrinsics as foxglove.CameraCalibration."""
    return f"{calibration_key(rsu_id, camera_id)}/camera_info"


# ---------------------------------------------------------------------------------------------- parsing


def _camera_key(key: str, last: str) -> tuple[str, str] | None:
    parts = key.split("/")
    is_camera_key = len(parts) == 5 and parts[0] == "rsu" and parts[2] == "camera" and parts[4] == last
    return (parts[1], parts[3]) if is_camera_key and parts[1] and parts[3] else None


def parse_detections_key(key: str) -> tuple[str, str] | None:
    """(rsu_id, camera_id) of `rsu/{rsu}/camera/{cam}/detections`, else None."""
    return _camera_key(key, "detections")


def parse_image_key(key: str) -> tuple[str, str] | None:
    """(rsu_id, camera_id) of `rsu/{rsu}/camera/{cam}/image`, else None."""
    return _camera_key(key, "image")


def parse_v2x_key(key: str) -> str | None:
    """The station segment of `v2x/cam/{station}` (not checked to be a number), else None."""
    parts = key.split("/")
    if len(parts) == 3 and parts[0] == "v2x" and parts[1] == "cam" and parts[2]:
        return parts[2]
    return None


def parse_alive_key(key: str) -> str | None:
    """The rsu_id of `rsu/{rsu}/alive`, else None."""
    parts = key.split("/")
    if len(parts) == 3 and parts[0] == "rsu" and parts[2] == "alive" and parts[1]:
        return parts[1]
    return None
