"""Offline calibration (`rsucal calibrate`): inputs from files, a progress bar, and readable reports.

Inputs come from an rsucal MCAP recording (one camera's detections, one V2X station's positions converted
to UTM poses) or from the reference toolbox's YAML pair (detections.yaml + poses.yaml, poses already in
absolute UTM). Either way the result is the CalibrationInputs that the daemon's jobs also build, so
`rsucal calibrate` and the service make the same pipeline call. Bad files raise InputError naming the file
and field; recoverable problems (rejected messages, a damaged chunk) are returned as notes.
"""

from __future__ import annotations

import math
import re
import sys
from collections import Counter
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from types import TracebackType
from typing import TYPE_CHECKING, TextIO

import numpy as np
from pyproj.exceptions import CRSError
from tqdm import tqdm

from daemon.keys import v2x_key
from pipeline.calibrate import CalibrationInputs, CalibrationOutcome
from pipeline.camera import lens_model_note
from pipeline.errors import InputError
from pipeline.frames import UtmFrame, poses_from_v2x, precise_v2x, utm_epsg_for
from pipeline.loaders import (
    load_intrinsics,
    load_toolbox_detection_table,
    load_toolbox_pose_table,
    load_vehicle,
)
from pipeline.tables import PoseTable
from schemas.atomic import write_atomic
from schemas.common import EPSG_PATTERN, IDENTIFIER, LOCAL_CRS, CameraIntrinsics, VehicleProfile
from schemas.config import DEFAULT_MAX_V2X_STD_M
from schemas.messages import VehiclePose
from schemas.results import CalibrationResult

if TYPE_CHECKING:
    from sim.simulate import SimulationResult

# The toolbox's poses.yaml is UTM without a zone; the reference data (and our simulator's German sites
# but Dresden) are zone 32N. Only the WGS84 output depends on it: R, t live in the UTM frame itself.
DEFAULT_YAML_CRS = "EPSG:32632"
OFFLINE_RSU_ID = "offline"
DEFAULT_CAMERA_ID = "camera"

_EPSG = re.compile(EPSG_PATTERN)
# Eastings inside a UTM zone lie within ~167-833 km (widest at the equator), northings within 0-10 000 km.
# Poses outside are not absolute UTM (typically a local frame), and their WGS84 output would be nonsense.
_UTM_EAST_RANGE_M = (100_000.0, 900_000.0)
_UTM_NORTH_RANGE_M = (0.0, 10_000_000.0)
_MAX_LISTED_CHOICES = 12


@dataclass(frozen=True, slots=True)
class OfflineInputs:
    """CalibrationInputs plus what was assumed or skipped while reading them (printed as notes)."""

    inputs: CalibrationInputs
    notes: tuple[str, ...] = ()


def load_offline_inputs(
    camera_path: Path | CameraIntrinsics,
    vehicle_path: Path,
    *,
    mcap_path: Path | None = None,
    detections_path: Path | None = None,
    poses_path: Path | None = None,
    camera_id: str | None = None,
    station_id: int | None = None,
    crs: str | None = None,
    time_offset_ns: int = 0,
    frame: str = "utm",
    origin: str | None = None,
    max_v2x_std_m: float = DEFAULT_MAX_V2X_STD_M,
) -> OfflineInputs:
    """Build one camera's CalibrationInputs from an MCAP recording or from the toolbox YAML pair.

    YAML poses in a local metric frame (the toolbox's published track): `frame="local"` keeps them there
    (result in crs LOCAL_CRS, no lat/lon); `origin="E,N"` with `crs` places that frame in the UTM zone, its
    axes along grid east and north, so the result is UTM with lat/lon.

    MCAP: the detections of `camera_id` (may be omitted when the file holds one camera) and the V2X
    positions of `station_id` (may be omitted when there is one station), converted to UTM poses in
    `crs` (default: the UTM zone of the first position), without those reported less accurate than
    `max_v2x_std_m` (pipeline.frames.precise_v2x). YAML: detections.yaml + poses.yaml (absolute UTM
    of `crs`, default DEFAULT_YAML_CRS); the camera id is `camera_id`, else camera.yaml's stem.
    """
    if (mcap_path is None) == (detections_path is None and poses_path is None):
        raise InputError("arguments", "give either --mcap REC.mcap or --detections D.yaml --poses P.yaml")
    if mcap_path is None and (detections_path is None or poses_path is None):
        missing = "--poses" if poses_path is None else "--detections"
        raise InputError(missing, "the YAML pair needs both --detections and --poses")
    if camera_id is not None and not IDENTIFIER.match(camera_id):
        raise InputError("--camera-id", f"{camera_id!r} is not a camera id ([A-Za-z0-9_.-], 1-64 chars)")
    if frame not in ("utm", "local"):
        raise InputError("--frame", f"{frame!r} is not one of utm, local")
    is_local = frame == "local" or origin is not None
    if is_local and mcap_path is not None:
        option = "--origin" if origin is not None else "--frame"
        raise InputError(
            option, "a recording's V2X positions are WGS84; a local frame applies to --poses only"
        )
    shift = _parsed_origin(origin) if origin is not None else None
    if shift is not None and crs is None:
        raise InputError("--origin", "needs --crs EPSG:N, the UTM zone the origin E,N is in")
    if frame == "local" and origin is None and crs is not None:
        raise InputError("--crs", "a local frame has no zone; give --origin E,N with --crs to place it")
    if crs is not None:
        crs = _checked_crs(crs, "--crs")
    # The intrinsics may come from a result (rsucal report) instead of camera.yaml.
    intrinsics = (
        camera_path if isinstance(camera_path, CameraIntrinsics) else load_intrinsics(Path(camera_path))
    )
    vehicle = load_vehicle(Path(vehicle_path))

    lens = lens_model_note(intrinsics)
    # Named by the camera file (a result's intrinsics: by the field alone).
    lens_notes = (
        []
        if lens is None
        else [lens if isinstance(camera_path, CameraIntrinsics) else f"{camera_path}: {lens}"]
    )
    if mcap_path is not None:
        loaded = _from_mcap(
            Path(mcap_path), intrinsics, vehicle, camera_id, station_id, crs, time_offset_ns, max_v2x_std_m
        )
        return replace(loaded, notes=(*lens_notes, *loaded.notes))
    assert detections_path is not None and poses_path is not None
    notes: list[str] = lens_notes
    if frame == "local" and shift is None:
        crs = LOCAL_CRS
        notes.append("poses in a local metric frame: the result stays in it, without lat/lon")
    elif crs is None:
        crs = DEFAULT_YAML_CRS
        notes.append(f"poses are UTM without a zone: assuming {crs} (set --crs for the lat/lon output)")
    if camera_id is None:
        stem = "" if isinstance(camera_path, CameraIntrinsics) else Path(camera_path).stem
        camera_id = stem if IDENTIFIER.match(stem) else DEFAULT_CAMERA_ID
    detections = load_toolbox_detection_table(Path(detections_path), camera_id)
    poses = load_toolbox_pose_table(Path(poses_path))
    if shift is not None:
        east, north = shift
        poses = poses.moved(east, north)
        notes.append(
            f"poses in a local frame placed at E {east} N {north} of {crs} (axes along grid east/north)"
        )
    if crs != LOCAL_CRS:
        _check_absolute_utm(Path(poses_path), poses, placed=shift is not None)
    inputs = CalibrationInputs(
        rsu_id=OFFLINE_RSU_ID,
        camera_id=camera_id,
        intrinsics=intrinsics,
        vehicle=vehicle,
        detections=detections,
        poses=poses,
        crs=crs,
        time_offset_ns=time_offset_ns,
        station_id=station_id,
        recordings=(str(detections_path), str(poses_path)),
    )
    return OfflineInputs(inputs, tuple(notes))


def _from_mcap(
    path: Path,
    intrinsics: CameraIntrinsics,
    vehicle: VehicleProfile,
    camera_id: str | None,
    station_id: int | None,
    crs: str | None,
    time_offset_ns: int,
    max_v2x_std_m: float,
) -> OfflineInputs:
    # Read every camera and station, then choose: a wrong or missing choice can then list the real ones.
    from daemon.recording import read_recording  # mcap: not loaded for the toolbox's YAML files

    recording = read_recording(path)
    notes = [f"{path}: {problem}" for problem in recording.problems]
    if not recording.complete:
        notes.append(f"{path}: not finished by its writer (no footer); read up to its last intact chunk")
    for topic, count in sorted(recording.rejected.items()):
        example = recording.rejection_examples.get(topic, "")
        notes.append(f"{path}: {count} message(s) on {topic} rejected, first: {example}")

    cameras = recording.camera_ids
    if not cameras:
        raise InputError(str(path), "detections: the recording holds no rsu/*/camera/*/detections messages")
    if camera_id is None:
        if len(cameras) > 1:
            raise InputError(
                str(path),
                f"detections: {len(cameras)} cameras ({_choices(cameras)}); choose one with --camera-id",
            )
        camera_id = cameras[0]
    elif camera_id not in recording.detections:
        raise InputError(
            str(path), f"detections: no camera {camera_id!r}; the recording has {_choices(cameras)}"
        )

    per_station = Counter(message.station_id for message in recording.v2x)
    if not per_station:
        raise InputError(
            str(path), "v2x: the recording holds no v2x/cam/* positions of a calibration vehicle"
        )
    listing = _choices([f"{sid} ({n} positions)" for sid, n in sorted(per_station.items())])
    if station_id is None:
        if len(per_station) > 1:
            raise InputError(
                str(path),
                f"v2x: {len(per_station)} stations ({listing}); "
                "name the calibration vehicle with --station-id",
            )
        station_id = next(iter(per_station))
    elif station_id not in per_station:
        raise InputError(str(path), f"v2x: no positions of station {station_id}; the recording has {listing}")
    messages = [message for message in recording.v2x if message.station_id == station_id]

    if crs is None:
        try:
            crs = utm_epsg_for(messages[0].lat, messages[0].lon)
        except InputError as err:
            raise InputError(str(path), f"{v2x_key(station_id)}: {err.detail}") from err
        notes.append(f"crs {crs}: the UTM zone of the first V2X position (--crs to override)")
    precise, left_out = precise_v2x(messages, max_v2x_std_m, "--max-v2x-std")
    if left_out:
        notes.append(f"{path}: {left_out}")
    poses, skipped = poses_from_v2x(precise, UtmFrame(crs))
    if skipped:
        notes.append(f"{path}: {skipped} V2X position(s) of station {station_id} not representable in {crs}")

    inputs = CalibrationInputs(
        rsu_id=recording.rsu_id or OFFLINE_RSU_ID,
        camera_id=camera_id,
        intrinsics=intrinsics,
        vehicle=vehicle,
        detections=recording.detections[camera_id],
        poses=poses,
        crs=crs,
        time_offset_ns=time_offset_ns,
        station_id=station_id,
        recordings=(str(path),),
        poses_left_out=left_out,
    )
    return OfflineInputs(inputs, tuple(notes))


def _checked_crs(crs: str, source: str) -> str:
    """'epsg:32632' -> 'EPSG:32632', and only UTM zones (the result schema stores exactly this form)."""
    normalised = crs.strip().upper()
    if not _EPSG.match(normalised):
        raise InputError(source, f"{crs!r} is not an EPSG code like EPSG:32632")
    try:
        UtmFrame(normalised)
    except InputError as err:
        raise InputError(source, err.detail) from err
    except CRSError as err:
        raise InputError(source, f"{crs!r} is not a known CRS ({err})") from err
    return normalised


def _parsed_origin(text: str) -> tuple[float, float]:
    """'E,N' (metres in the UTM zone of --crs) -> (E, N)."""
    parts = text.split(",")
    try:
        values = [float(part) for part in parts]
    except ValueError:
        values = []
    if len(values) != 2 or not all(math.isfinite(v) for v in values):
        raise InputError(
            "--origin", f"{text!r} is not E,N: two finite numbers in metres, e.g. 572000,5361000"
        )
    east, north = values
    for name, value, (low, high) in (("E", east, _UTM_EAST_RANGE_M), ("N", north, _UTM_NORTH_RANGE_M)):
        if not low < value < high:
            raise InputError(
                "--origin", f"{name} = {value} is not a UTM coordinate ({low:.0f} < {name} < {high:.0f} m)"
            )
    return east, north


def _check_absolute_utm(path: Path, poses: Sequence[VehiclePose], placed: bool = False) -> None:
    rows: Iterable[tuple[int, float, float]]
    if isinstance(poses, PoseTable):
        x, y = poses.values[:, 0], poses.values[:, 1]
        is_inside = (x > _UTM_EAST_RANGE_M[0]) & (x < _UTM_EAST_RANGE_M[1])
        is_inside &= (y > _UTM_NORTH_RANGE_M[0]) & (y < _UTM_NORTH_RANGE_M[1])
        if is_inside.all():
            return
        first = int(np.argmin(is_inside))  # the first pose outside, reported as below
        rows = [(int(poses.stamps[first]), float(x[first]), float(y[first]))]
    else:
        rows = ((pose.stamp_ns, pose.x, pose.y) for pose in poses)
    for stamp_ns, east, north in rows:
        for name, value, (low, high) in (("x", east, _UTM_EAST_RANGE_M), ("y", north, _UTM_NORTH_RANGE_M)):
            if not low < value < high:
                where = " once placed at --origin" if placed else ""
                raise InputError(
                    str(path),
                    f"{stamp_ns}.{name}: {value} is not a UTM coordinate{where} (expected {low:.0f} < "
                    f"{name} < {high:.0f} m); for poses in a local metric frame use --frame local "
                    "(or --origin E,N --crs EPSG:N to place the frame)",
                )


def _choices(values: Sequence[str]) -> str:
    shown = ", ".join(values[:_MAX_LISTED_CHOICES])
    more = len(values) - _MAX_LISTED_CHOICES
    return f"{shown}, ... {more} more" if more > 0 else shown


# ---------------------------------------------------------------------------------------------- output


def write_result(result: CalibrationResult, path: Path) -> Path:
    """Write the result JSON atomically and durably (schemas.atomic): never a half-written file."""
    path = Path(path)
    try:
        write_atomic(path, (result.model_dump_json(indent=2) + "\n").encode("utf-8"))
    except OSError as err:
        raise InputError(str(path), f"(file): cannot write: {err.strerror or err}") from err
    return path


class TerminalProgress:
    """A tqdm bar on `stream` driven by calibrate()'s progress callback; silent unless it is a terminal."""

    def __init__(self, stream: TextIO | None = None) -> None:
        stream = stream if stream is not None else sys.stderr
        self._bar = tqdm(
            total=100,
            file=stream,
            disable=not stream.isatty(),
            leave=False,
            mininterval=0.0,  # calibrate() reports ~10 times per run: draw every stage as it starts
            bar_format="{desc:<12} {bar} {percentage:3.0f}% {elapsed}",
        )

    def __call__(self, stage: str, fraction: float) -> None:
        self._bar.set_description_str(stage, refresh=False)
        target = min(100, max(0, round(100.0 * fraction)))
        if target > self._bar.n:
            self._bar.update(target - self._bar.n)
        else:
            self._bar.refresh()

    def close(self) -> None:
        self._bar.close()

    def __enter__(self) -> TerminalProgress:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()


def format_stage_reports(outcome: CalibrationOutcome) -> str:
    """What each stage kept and discarded and why, then the candidate groups (for --verbose)."""
    lines = ["stages:"]
    for report in outcome.stages:
        lines.append(f"  {report.stage:<12} kept {report.kept}, discarded {report.discarded}")
        lines.extend(f"    {line}" for line in report.lines())
    if outcome.candidates:
        origin = np.asarray(outcome.result.frame.origin, dtype=np.float64)
        lines.append("candidate groups (* chosen):")
        for candidate in outcome.candidates:
            mark = "*" if candidate is outcome.chosen else " "
            centre = candidate.whole_box.camera_centre + origin
            lines.append(
                f"  {mark} tracks {list(candidate.track_ids)}: {candidate.traversals} traversal(s), "
                f"box error {100.0 * candidate.box_error_rel:.2f} %, "
                f"delta_p mean {candidate.delta_p_mean_m:.3f} m, "
                f"camera at E {centre[0]:.2f} N {centre[1]:.2f} h {centre[2]:.2f} m"
            )
    return "\n".join(lines)


def format_summary(result: CalibrationResult, written: Path | None = None) -> str:
    """The short report printed after every run: verdict, camera position, quality, uncertainty."""
    verdict = result.verdict
    lines = [f"verdict      {verdict.status} (camera {result.camera_id}, rsu {result.rsu_id})"]
    lines.extend(f"  reason     {reason}" for reason in verdict.reasons)
    position = result.camera_position
    if position is not None:
        east, north, height = position.utm
        if position.lat is not None and position.lon is not None and position.alt is not None:
            lines.append(f"position     {result.frame.crs} E {east:.3f} N {north:.3f} h {height:.3f} m")
            lines.append(
                f"             lat {position.lat:.7f} lon {position.lon:.7f} alt {position.alt:.3f} m"
            )
        else:
            lines.append(f"position     local frame x {east:.3f} y {north:.3f} z {height:.3f} m (no lat/lon)")
    quality = result.quality
    if quality is not None:
        # Labels say what the figures are measured on: rsucal evaluate scores other boxes against the true
        # footprints, and the daemon counts drive-pasts through coverage (docs/method.md, "Three numbers").
        lines.append(
            f"delta_p      mean {quality.delta_p_mean_m:.3f} m, max {quality.delta_p_max_m:.3f} m "
            "(fitted boxes vs reported poses)"
        )
        lines.append(f"e            mean {quality.e_mean_pct:.3f} %, max {quality.e_max_pct:.3f} %")
        lines.append(
            f"traversals   {quality.traversals} in the fit ({quality.tracks} tracks, "
            f"{quality.correspondences} correspondences, box RMSE {quality.reprojection_rmse_px:.2f} px)"
        )
    uncertainty = result.uncertainty
    if uncertainty is not None:
        lines.append(
            f"std          position {uncertainty.position_std_m:.3f} m, "
            f"rotation {uncertainty.rotation_std_deg:.3f} deg"
        )
    if written is not None:
        lines.append(f"wrote        {written}")
    return "\n".join(lines)


def inputs_from_simulation(result: SimulationResult, camera_id: str | None = None) -> CalibrationInputs:
    """calibrate() inputs for one camera of a simulation (default: the first), exactly as a recording of
    the same scene would be calibrated: the vehicle's poses from its V2X broadcasts where it sends CAMs (as
    the daemon does), else its IMU poses (the toolbox's poses.yaml); the simulated vehicle clock offset is
    passed as the configured one. The camera's latency is not passed: rsucal does not know it."""
    if result.v2x_mode == "cam":
        precise, _ = precise_v2x(result.v2x, DEFAULT_MAX_V2X_STD_M, "gates.max_v2x_std_m")
        poses, _ = poses_from_v2x(precise, UtmFrame(result.origin.crs))
    else:
        poses = result.poses
    camera = (
        result.cameras[0]
        if camera_id is None
        else next(c for c in result.cameras if c.camera_id == camera_id)
    )
    return CalibrationInputs(
        rsu_id=result.rsu_id,
        camera_id=camera.camera_id,
        intrinsics=camera.intrinsics,
        vehicle=result.vehicle,
        detections=result.detections[camera.camera_id],
        poses=poses,
        crs=result.origin.crs,
        time_offset_ns=result.ground_truth[camera.camera_id].clock_offset_ns,
        station_id=result.station_id,
    )
