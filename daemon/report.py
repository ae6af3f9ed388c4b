"""`rsucal report` and the daemon's per-job report: one self-contained HTML file (figures embedded) and PNGs.

Input: a CalibrationResult and the CalibrationOutcome of the calibrate() call that made it (the daemon's job
has it; `rsucal report` re-runs calibrate() on the same recording or YAML pair and says whether the re-run
reproduced the result). Every figure that depends on the pose uses the RESULT's pose; the hypotheses and
groups come from the run. Figures (matplotlib, Agg, headless):
  overlay-N.png     per drive-past: the calibration vehicle's cuboid projected with the result over its
                    detected box and the frame's other boxes (a rendered frame: no image is recorded)
  map.png           top down: camera, its view on the ground (coverage), the vehicle's path, its boxes'
                    positions coloured by delta_p
  distance.png      delta_p and whole-box error against distance (the paper's Fig. 3)
  residuals.png     delta_p and box error per drive-past
  hypotheses.png    each track's EPnP camera position, by group; the chosen group and the result
  uncertainty.png   the camera position's 1/2/3-sigma ellipses (east-north and east/north-up)
"""

from __future__ import annotations

import base64
import html
import io
import math
import time
from collections.abc import Callable, Collection, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # headless: no display on a roadside computer, and never a GUI backend by accident

import cv2
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.figure import Figure
from matplotlib.patches import Ellipse, Polygon, Rectangle

from pipeline.association import MatchedTrack
from pipeline.calibrate import CalibrationDiagnostics, CalibrationOutcome
from pipeline.camera import CameraModel, camera_centre, pose_distance, project_points, undistort_pixels
from pipeline.metrics import delta_p
from pipeline.refinement import RefinementParams, box_residuals
from pipeline.vehicle import body_corners, footprint_corners
from schemas.atomic import write_atomic
from schemas.common import VehicleProfile
from schemas.config import DEFAULT_MAX_V2X_STD_M
from schemas.messages import DetectionFrame
from schemas.results import CalibrationResult

# A new drive-past starts when the calibration vehicle's chosen tracks leave a gap of at least this long.
TRAVERSAL_GAP_NS = 2_000_000_000
COVERAGE_RANGE_M = 120.0  # the view drawn on the map ends this far from the camera
DPI = 110
# The cuboid's 12 edges over body_corners' order: footprint 0-3 (RR, FR, FL, RL), roof 4-7 above them.
_CUBOID_EDGES = (
    (0, 1),
    (1, 2),
    (2, 3),
    (3, 0),
    (4, 5),
    (5, 6),
    (6, 7),
    (7, 4),
    (0, 4),
    (1, 5),
    (2, 6),
    (3, 7),
)
_TRAVERSAL_COLOURS = plt.get_cmap("tab10")


@dataclass(frozen=True, slots=True)
class Figures:
    """Each figure as PNG bytes, by file name (overlay-1.png, map.png, ...), in report order."""

    png: dict[str, bytes]


@dataclass(frozen=True, slots=True)
class _Boxes:
    """The chosen group's boxes with the result's pose: per box its track, stamp, drive-past, errors."""

    track_ids: np.ndarray  # (N,) int
    stamps: np.ndarray  # (N,) int64 ns
    boxes: np.ndarray  # (N, 4) px
    poses: np.ndarray  # (N, 6) local frame of the run
    traversal: np.ndarray  # (N,) int, 0-based
    delta_p_m: np.ndarray  # (N,) NaN where not valid
    box_error_pct: np.ndarray  # (N,) max |edge residual| / box height, %, NaN when every edge is clipped
    distance_m: np.ndarray  # (N,) camera centre to the vehicle's footprint centre


def _pose_in_run_frame(
    result: CalibrationResult, diagnostics: CalibrationDiagnostics
) -> tuple[np.ndarray, np.ndarray]:
    """The result's (R, t) expressed in the run's local frame (the two origins may differ)."""
    if result.R is None or result.t is None:
        raise ValueError(f"result {result.result_id} has no pose")
    R = np.asarray(result.R, dtype=np.float64)
    t = np.asarray(result.t, dtype=np.float64)
    run_origin = np.array([diagnostics.origin.x, diagnostics.origin.y, diagnostics.origin.z])
    # X_cam = R (X_utm - o_result) + t = R (X_utm - o_run) + R (o_run - o_result) + t
    return R, t + R @ (run_origin - np.asarray(result.frame.origin, dtype=np.float64))


def _traversal_labels(tracks: Sequence[MatchedTrack]) -> dict[int, int]:
    """track id -> drive-past index: tracks by start, a new drive-past after a gap of TRAVERSAL_GAP_NS."""
    labels: dict[int, int] = {}
    current_end: int | None = None
    index = -1
    for track in sorted(tracks, key=lambda m: int(m.stamps[0])):
        start, end = int(track.stamps[0]), int(track.stamps[-1])
        if current_end is None or start - current_end >= TRAVERSAL_GAP_NS:
            index += 1
            current_end = end
        current_end = max(current_end, end)
        labels[track.track_id] = index
    return labels


def _chosen_boxes(
    chosen: Sequence[MatchedTrack], R: np.ndarray, t: np.ndarray, camera: CameraModel, vehicle: VehicleProfile
) -> _Boxes:
    labels = _traversal_labels(chosen)
    boxes = np.concatenate([m.boxes for m in chosen])
    poses = np.concatenate([m.poses for m in chosen])
    footprints = footprint_corners(poses, vehicle)
    errors = delta_p(boxes, footprints, R, t, camera)
    residuals, heights = box_residuals(R, t, chosen, camera, vehicle, RefinementParams())
    with np.errstate(invalid="ignore", divide="ignore"):
        all_clipped = np.all(np.isnan(residuals), axis=1)
        misfit = np.nanmax(np.where(np.isnan(residuals), -np.inf, np.abs(residuals)), axis=1)
        box_error_pct = np.where(all_clipped, np.nan, 100.0 * misfit / heights)
    centre = camera_centre(R, t)
    return _Boxes(
        track_ids=np.concatenate([np.full(len(m.stamps), m.track_id) for m in chosen]),
        stamps=np.concatenate([m.stamps for m in chosen]),
        boxes=boxes,
        poses=poses,
        traversal=np.concatenate([np.full(len(m.stamps), labels[m.track_id]) for m in chosen]),
        delta_p_m=np.where(errors.valid, errors.delta_p_m, np.nan),
        box_error_pct=box_error_pct,
        distance_m=np.linalg.norm(footprints.mean(axis=1) - centre, axis=1),
    )


def _png(figure: Figure) -> bytes:
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", dpi=DPI)
    plt.close(figure)
    return buffer.getvalue()


def _overlay_row(index: int, data: _Boxes, imaged: Collection[int] = ()) -> int:
    """The box of drive-past `index` to draw: the largest (the vehicle closest to the camera), among the
    frames with a recorded image (`imaged`, stamps) when the drive-past has any."""
    rows = np.flatnonzero(data.traversal == index)
    with_image = rows[np.isin(data.stamps[rows], np.fromiter(imaged, dtype=np.int64, count=len(imaged)))]
    rows = with_image if len(with_image) else rows
    areas = (data.boxes[rows, 2] - data.boxes[rows, 0]) * (data.boxes[rows, 3] - data.boxes[rows, 1])
    return int(rows[int(np.argmax(areas))])


def _overlay(
    index: int,
    row: int,
    data: _Boxes,
    frames_by_stamp: dict[int, DetectionFrame],
    R: np.ndarray,
    t: np.ndarray,
    camera: CameraModel,
    vehicle: VehicleProfile,
    image: np.ndarray | None = None,
) -> bytes:
    """Row `row` of drive-past `index`: all boxes of its frame, the vehicle's box, the cuboid projected with
    the result and the vehicle's path, on the recorded image (BGR) if there is one, else a rendered frame."""
    figure, axes = plt.subplots(figsize=(8.0, 8.0 * camera.height / camera.width + 0.6))
    if image is not None:
        axes.imshow(image[:, :, ::-1], extent=(0, image.shape[1], image.shape[0], 0))
    else:
        axes.add_patch(Rectangle((0, 0), camera.width, camera.height, color="#30343a"))
    frame = frames_by_stamp.get(int(data.stamps[row]))
    for box in frame.boxes if frame is not None else ():
        axes.add_patch(
            Rectangle((box.x1, box.y1), box.x2 - box.x1, box.y2 - box.y1, fill=False, ec="#5aa9ff", lw=1.0)
        )
    x1, y1, x2, y2 = data.boxes[row]
    axes.add_patch(
        Rectangle((x1, y1), x2 - x1, y2 - y1, fill=False, ec="#ff6a1a", lw=2.5, label="detected box")
    )
    corners = body_corners(data.poses[row : row + 1], vehicle)[0]
    pixels, depth = project_points(corners, R, t, camera)
    for a, b in _CUBOID_EDGES:
        if depth[a] > 0 and depth[b] > 0:
            axes.plot(pixels[[a, b], 0], pixels[[a, b], 1], color="#5cff7a", lw=1.6)
    axes.plot([], [], color="#5cff7a", lw=1.6, label="vehicle model, result's pose")
    path = data.poses[data.traversal == index][:, :3]
    path_px, path_depth = project_points(path, R, t, camera)
    axes.plot(
        path_px[path_depth > 0, 0], path_px[path_depth > 0, 1], ":", color="#dddddd", lw=1.0, label="path"
    )
    axes.set_xlim(0, camera.width)
    axes.set_ylim(camera.height, 0)
    axes.set_aspect("equal")
    residual = data.delta_p_m[row]
    axes.set_title(
        f"drive-past {index + 1}: frame {int(data.stamps[row])} ns, track {int(data.track_ids[row])}, "
        f"delta_p {residual:.2f} m, box error {data.box_error_pct[row]:.1f} %"
        if math.isfinite(residual)
        else f"drive-past {index + 1}: frame {int(data.stamps[row])} ns, track {int(data.track_ids[row])}",
        fontsize=9,
    )
    axes.legend(loc="lower right", fontsize=8, framealpha=0.6)
    figure.tight_layout()
    return _png(figure)


def _ground_of_view(
    R: np.ndarray, t: np.ndarray, camera: CameraModel, diagnostics: CalibrationDiagnostics
) -> np.ndarray:
    """Where the image border's rays meet the ground (capped at COVERAGE_RANGE_M): the view's outline."""
    centre = camera_centre(R, t)
    w, h = camera.width, camera.height
    border = np.concatenate(
        [
            np.column_stack([np.linspace(0, w, 40), np.zeros(40)]),
            np.column_stack([np.full(40, w), np.linspace(0, h, 40)]),
            np.column_stack([np.linspace(w, 0, 40), np.full(40, h)]),
            np.column_stack([np.zeros(40), np.linspace(h, 0, 40)]),
        ]
    )
    normalized = undistort_pixels(border, camera)
    rays_cam = np.column_stack([normalized, np.ones(len(normalized))])
    rays = rays_cam @ R  # camera -> local: R^T applied to each row
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    ground = diagnostics.ground
    hits = ground.intersect_rays(centre, rays) if ground is not None else np.full_like(rays, np.nan)
    far = centre + COVERAGE_RANGE_M * rays
    distance = np.linalg.norm(hits - centre, axis=1)
    use_far = ~np.isfinite(distance) | (distance > COVERAGE_RANGE_M)
    outline = np.where(use_far[:, None], far, hits)
    return np.vstack([centre[None, :2], outline[:, :2], centre[None, :2]])


def _map(
    data: _Boxes, R: np.ndarray, t: np.ndarray, camera: CameraModel, diagnostics: CalibrationDiagnostics
) -> bytes:
    centre = camera_centre(R, t)
    span = np.concatenate([data.poses[:, :2], centre[None, :2]])
    low, high = span.min(axis=0) - 25.0, span.max(axis=0) + 25.0
    aspect = (high[1] - low[1]) / (high[0] - low[0])
    figure, axes = plt.subplots(figsize=(9.0, float(np.clip(7.5 * aspect + 1.2, 3.5, 11.0))))
    axes.add_patch(
        Polygon(
            _ground_of_view(R, t, camera, diagnostics),
            closed=True,
            fc="#5aa9ff",
            alpha=0.15,
            ec="#5aa9ff",
            label=f"view on the ground (to {COVERAGE_RANGE_M:.0f} m)",
        )
    )
    path = diagnostics.trajectory.poses
    axes.plot(path[:, 0], path[:, 1], color="#aaaaaa", lw=0.8, label="calibration vehicle's path")
    shown = np.isfinite(data.delta_p_m)
    scatter = axes.scatter(
        data.poses[shown, 0],
        data.poses[shown, 1],
        c=data.delta_p_m[shown],
        cmap="viridis_r",
        s=10,
        vmin=0.0,
        vmax=max(0.3, float(np.nanpercentile(data.delta_p_m, 95))) if shown.any() else 0.3,
        label="its boxes (position at the stamp)",
    )
    figure.colorbar(scatter, ax=axes, label="delta_p (m)", shrink=0.6)
    axes.plot(*centre[:2], marker="^", color="#d62728", markersize=12, ls="", label="camera")
    axis_z = R[2]  # the optical axis in the local frame
    if np.hypot(axis_z[0], axis_z[1]) > 1e-6:
        direction = axis_z[:2] / np.hypot(axis_z[0], axis_z[1])
        axes.annotate(
            "",
            xy=(float(centre[0] + 15.0 * direction[0]), float(centre[1] + 15.0 * direction[1])),
            xytext=(float(centre[0]), float(centre[1])),
            arrowprops={"arrowstyle": "->", "color": "#d62728", "lw": 2},
        )
    for index in np.unique(data.traversal):
        first = data.poses[data.traversal == index][0]
        axes.annotate(f"{index + 1}", first[:2], fontsize=9, color=_TRAVERSAL_COLOURS(index % 10))
    axes.set_xlim(low[0], high[0])
    axes.set_ylim(low[1], high[1])
    axes.set_aspect("equal")
    axes.set_xlabel("east of the local origin (m)")
    axes.set_ylabel("north (m)")
    axes.set_title("top-down: camera, view, drive-pasts (numbered) coloured by delta_p", fontsize=10)
    axes.legend(loc="best", fontsize=8, framealpha=0.7)
    figure.tight_layout()
    return _png(figure)


def _distance(data: _Boxes) -> bytes:
    figure, (top, bottom) = plt.subplots(2, 1, figsize=(8.0, 7.0), sharex=True)
    for index in np.unique(data.traversal):
        rows = data.traversal == index
        colour = _TRAVERSAL_COLOURS(index % 10)
        top.scatter(
            data.distance_m[rows], data.delta_p_m[rows], s=8, color=colour, label=f"drive-past {index + 1}"
        )
        bottom.scatter(data.distance_m[rows], data.box_error_pct[rows], s=8, color=colour)
    top.set_ylabel("delta_p (m)")
    top.set_title("delta_p and box error against distance (paper Fig. 3)", fontsize=10)
    top.legend(fontsize=8)
    top.grid(alpha=0.3)
    bottom.set_ylabel("box error: max |edge residual| / box height (%)")
    bottom.set_xlabel("distance camera - vehicle (m)")
    bottom.grid(alpha=0.3)
    figure.tight_layout()
    return _png(figure)


def _residuals(data: _Boxes) -> bytes:
    indices = [int(i) for i in np.unique(data.traversal)]
    figure, (left, right) = plt.subplots(1, 2, figsize=(9.0, 4.2))
    for axes, values, label in (
        (left, data.delta_p_m, "delta_p (m)"),
        (right, data.box_error_pct, "box error (%)"),
    ):
        groups = [values[(data.traversal == i) & np.isfinite(values)] for i in indices]
        positions = [i + 1 for i, g in zip(indices, groups, strict=True) if len(g)]
        axes.boxplot([g for g in groups if len(g)], positions=positions, showfliers=True)
        axes.set_xlabel("drive-past")
        axes.set_ylabel(label)
        axes.grid(alpha=0.3)
        counts = [len(g) for g in groups]
        axes.set_title(
            " ".join(f"#{i + 1}: {n} boxes" for i, n in zip(indices, counts, strict=True)), fontsize=8
        )
    figure.suptitle("residuals per drive-past (the result's pose)", fontsize=10)
    figure.tight_layout()
    return _png(figure)


def _hypotheses(
    outcome: CalibrationOutcome, diagnostics: CalibrationDiagnostics, centre: np.ndarray, chosen_ids: set[int]
) -> bytes:
    """Each track's hypothesis camera position by group: overview top down, then zoomed on the result (top
    down and east against height), where the chosen group's members and the refined candidates lie."""
    figure, (overview, zoom, side) = plt.subplots(1, 3, figsize=(13.0, 4.6))
    group_of: dict[int, int] = {}
    for number, group in enumerate(diagnostics.groups):
        for track_id in group:
            group_of.setdefault(track_id, number)
    near: list[np.ndarray] = [centre]
    for hypothesis in diagnostics.hypotheses:
        c = hypothesis.camera_centre
        group_number = group_of.get(hypothesis.track_id)
        is_chosen = hypothesis.track_id in chosen_ids
        colour = "#bbbbbb" if group_number is None else _TRAVERSAL_COLOURS(group_number % 10)
        style = {
            "marker": "o",
            "s": 70 if is_chosen else 24,
            "color": colour,
            "edgecolors": "black" if is_chosen else "none",
            "linewidths": 1.2,
            "zorder": 3,
        }
        overview.scatter(c[0], c[1], **style)
        zoom.scatter(c[0], c[1], **style)
        side.scatter(c[0], c[2], **style)
        if group_number is not None or is_chosen:
            near.append(c)
    for number in range(len(diagnostics.groups)):
        overview.scatter([], [], color=_TRAVERSAL_COLOURS(number % 10), s=24, label=f"group {number + 1}")
    overview.scatter([], [], color="#bbbbbb", s=24, label="in no group")
    overview.scatter([], [], color="white", edgecolors="black", s=70, label="chosen group's tracks")
    for candidate in outcome.candidates:
        c = candidate.whole_box.camera_centre
        near.append(c)
        for axes, k in ((overview, 1), (zoom, 1), (side, 2)):
            axes.plot(c[0], c[k], "x", color="black", markersize=9, mew=2, zorder=4)
    overview.plot([], [], "x", color="black", mew=2, label="refined candidates")
    for axes, k in ((overview, 1), (zoom, 1), (side, 2)):
        axes.plot(
            centre[0],
            centre[k],
            marker="*",
            mfc="none",
            mec="#d62728",
            mew=2,
            markersize=20,
            ls="",
            zorder=5,
            label="result" if axes is overview else None,
        )
        axes.grid(alpha=0.3)
        axes.set_xlabel("east (m)")
    # The zoom shows the groups' members and candidates around the result (at least +-3 m).
    points = np.array(near)
    reach = max(3.0, 1.2 * float(np.max(np.abs(points - centre)[:, :2])) if len(points) > 1 else 3.0)
    reach = min(reach, 50.0)
    zoom.set_xlim(centre[0] - reach, centre[0] + reach)
    zoom.set_ylim(centre[1] - reach, centre[1] + reach)
    side.set_xlim(centre[0] - reach, centre[0] + reach)
    side.set_ylim(centre[2] - reach, centre[2] + reach)
    for axes in (overview, zoom):
        axes.set_ylabel("north (m)")
        axes.set_aspect("equal", adjustable="datalim" if axes is overview else "box")
    side.set_ylabel("up (m)")
    side.set_aspect("equal", adjustable="box")
    overview.set_title("hypotheses' camera positions (EPnP), top down", fontsize=9)
    zoom.set_title(f"zoomed on the result (+-{reach:.0f} m)", fontsize=9)
    side.set_title("the same, east against height", fontsize=9)
    overview.legend(fontsize=7, loc="best", framealpha=0.7)
    figure.tight_layout()
    return _png(figure)


def _uncertainty(result: CalibrationResult) -> bytes | None:
    if result.uncertainty is None:
        return None
    covariance = np.asarray(result.uncertainty.covariance, dtype=np.float64)[3:, 3:]  # camera position, m^2
    figure, axes_pair = plt.subplots(1, 2, figsize=(9.0, 4.4))
    for axes, (i, j), labels in (
        (axes_pair[0], (0, 1), ("east (m)", "north (m)")),
        (axes_pair[1], (0, 2), ("east (m)", "up (m)")),
    ):
        block = covariance[np.ix_([i, j], [i, j])]
        values, vectors = np.linalg.eigh(block)
        values = np.clip(values, 0.0, None)
        angle = math.degrees(math.atan2(vectors[1, 1], vectors[0, 1]))
        reach = 0.0
        for k, alpha in ((1, 0.5), (2, 0.3), (3, 0.15)):
            width, height = 2 * k * math.sqrt(values[1]), 2 * k * math.sqrt(values[0])
            axes.add_patch(
                Ellipse(
                    (0.0, 0.0),
                    width,
                    height,
                    angle=angle,
                    fc="#5aa9ff",
                    alpha=alpha,
                    ec="#1f5fa8",
                    label=f"{k} sigma",
                )
            )
            reach = max(reach, width / 2, height / 2)
        reach = max(reach * 1.2, 0.05)
        axes.set_xlim(-reach, reach)
        axes.set_ylim(-reach, reach)
        axes.set_aspect("equal")
        axes.axhline(0, color="#888888", lw=0.5)
        axes.axvline(0, color="#888888", lw=0.5)
        axes.set_xlabel(labels[0])
        axes.set_ylabel(labels[1])
        axes.grid(alpha=0.3)
    axes_pair[0].legend(fontsize=8)
    figure.suptitle(
        f"camera position uncertainty: position std {result.uncertainty.position_std_m:.3f} m "
        f"(worst axis), rotation std {result.uncertainty.rotation_std_deg:.3f} deg",
        fontsize=9,
    )
    figure.tight_layout()
    return _png(figure)


ImageSource = Callable[[Sequence[int]], Mapping[int, bytes]]
"""Recorded images (compressed JPEG/PNG bytes) for detection stamps; stamps without one are left out."""


def _decoded(images: Mapping[int, bytes], stamp_ns: int) -> np.ndarray | None:
    data = images.get(stamp_ns)
    if data is None:
        return None
    image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    return image if image is not None and image.ndim == 3 else None  # undecodable: the rendered frame


def render_figures(
    result: CalibrationResult,
    outcome: CalibrationOutcome,
    vehicle: VehicleProfile,
    detections: Sequence[DetectionFrame],
    images: ImageSource | None = None,
) -> Figures:
    """Every figure the run allows (a refused run may have no chosen group or no pose: fewer figures).

    `images` supplies recorded images for the overlays' frames, drawn under them when they decode."""
    png: dict[str, bytes] = {}
    diagnostics = outcome.diagnostics
    if diagnostics is None or result.R is None or result.t is None:
        return Figures(png)
    camera = CameraModel.from_intrinsics(result.intrinsics)
    R, t = _pose_in_run_frame(result, diagnostics)
    centre = camera_centre(R, t)
    chosen_ids = set(outcome.chosen.track_ids) if outcome.chosen is not None else set()
    chosen = [m for m in diagnostics.tracks if m.track_id in chosen_ids]
    if chosen:
        data = _chosen_boxes(chosen, R, t, camera, vehicle)
        frames_by_stamp = {frame.stamp_ns: frame for frame in detections}
        # A recording may hold images of some frames only (`rsucal simulate --images 5`): ask for every frame
        # of the vehicle, and draw each drive-past on one that has an image.
        recorded = images([int(stamp) for stamp in data.stamps]) if images is not None else {}
        rows = {
            index: _overlay_row(index, data, recorded.keys())
            for index in sorted({int(i) for i in data.traversal})
        }
        for index, row in rows.items():
            image = _decoded(recorded, int(data.stamps[row]))
            png[f"overlay-{index + 1}.png"] = _overlay(
                index, row, data, frames_by_stamp, R, t, camera, vehicle, image
            )
        png["map.png"] = _map(data, R, t, camera, diagnostics)
        png["distance.png"] = _distance(data)
        png["residuals.png"] = _residuals(data)
    if diagnostics.hypotheses:
        png["hypotheses.png"] = _hypotheses(outcome, diagnostics, centre, chosen_ids)
    uncertainty = _uncertainty(result)
    if uncertainty is not None:
        png["uncertainty.png"] = uncertainty
    return Figures(png)


# ---------------------------------------------------------------------------------------------- HTML

_CAPTIONS = {
    "map.png": "Top down, local frame: the camera (red), its view on the ground, the calibration vehicle's "
    "path and the positions of its boxes coloured by delta_p; numbers mark where each drive-past starts.",
    "distance.png": "delta_p (paper Sec. IV-B) and the whole-box error against the camera-vehicle distance, "
    "as in the paper's Fig. 3.",
    "residuals.png": "Residuals of the result's pose per drive-past; one drive-past far off the others is a "
    "warning.",
    "hypotheses.png": "Camera positions of the single-track hypotheses (EPnP + RANSAC), coloured by group; "
    "ringed: the chosen group's tracks; crosses: refined candidates; star: the result.",
    "uncertainty.png": "1, 2 and 3 sigma of the camera position (the published covariance, inflated as "
    "validated).",
}


def _verdict_words(result: CalibrationResult) -> str:
    if result.verdict.is_accepted:
        words = "Accepted: every validation gate passed; this calibration may be used."
    else:
        words = "Refused: this calibration must not be used."
    reasons = "".join(f"<li>{html.escape(reason)}</li>" for reason in result.verdict.reasons)
    return f"<p class='{result.verdict.status}'>{words}</p>" + (f"<ul>{reasons}</ul>" if reasons else "")


def _table(rows: Sequence[tuple[str, str]]) -> str:
    body = "".join(f"<tr><th>{html.escape(k)}</th><td>{html.escape(v)}</td></tr>" for k, v in rows)
    return f"<table>{body}</table>"


def _facts(result: CalibrationResult) -> list[tuple[str, str]]:
    rows = [
        ("RSU / camera", f"{result.rsu_id} / {result.camera_id}"),
        ("result id", result.result_id),
        ("created", f"{result.created_at_ns} ns"),
        ("frame", f"{result.frame.crs}, origin {result.frame.origin}"),
    ]
    if result.camera_position is not None:
        p = result.camera_position
        if p.lat is not None and p.lon is not None and p.alt is not None:
            where = (
                f"lat {p.lat:.7f}, lon {p.lon:.7f}, alt {p.alt:.2f} m; UTM "
                f"{p.utm[0]:.2f} E, {p.utm[1]:.2f} N, {p.utm[2]:.2f} m"
            )
        else:  # a result in a local metric frame (calibrate --frame local): no geographic position
            where = f"local frame x {p.utm[0]:.2f}, y {p.utm[1]:.2f}, z {p.utm[2]:.2f} m (no lat/lon)"
        rows.append(("camera position", where))
    if result.quality is not None:
        q = result.quality
        rows += [
            ("delta_p mean / max", f"{q.delta_p_mean_m:.3f} m / {q.delta_p_max_m:.3f} m"),
            ("e mean / max", f"{q.e_mean_pct:.2f} % / {q.e_max_pct:.2f} %"),
            ("reprojection RMSE", f"{q.reprojection_rmse_px:.2f} px"),
            ("evidence", f"{q.correspondences} residuals, {q.tracks} tracks, {q.traversals} drive-pasts"),
        ]
    if result.uncertainty is not None:
        rows.append(
            (
                "uncertainty",
                f"position std {result.uncertainty.position_std_m:.3f} m, rotation std "
                f"{result.uncertainty.rotation_std_deg:.3f} deg",
            )
        )
    if result.change is not None:
        c = result.change
        rows.append(
            (
                "change",
                f"{c.shift_m:.2f} m / {c.shift_deg:.2f} deg from {c.previous_result_id}"
                + (" (moved)" if c.moved else ""),
            )
        )
    provenance = result.provenance
    if provenance.recordings:
        rows.append(("data", ", ".join(provenance.recordings)))
    if provenance.window_start_ns is not None and provenance.window_end_ns is not None:
        rows.append(
            (
                "window",
                f"{provenance.window_start_ns} .. {provenance.window_end_ns} ns "
                f"({(provenance.window_end_ns - provenance.window_start_ns) / 1e9:.0f} s)",
            )
        )
    rows.append(("software", f"{provenance.software_version}, config {provenance.config_hash or '-'}"))
    return rows


def report_html(result: CalibrationResult, figures: Figures, notes: Sequence[str] = ()) -> str:
    """The report as one self-contained HTML document (figures inlined as data: URIs)."""
    sections = []
    for name, data in figures.png.items():
        caption = _CAPTIONS.get(
            name,
            "The calibration vehicle's cuboid projected with the result (green) over "
            "its detected box (orange) and the frame's other boxes (blue), on a rendered "
            "frame; dotted: its path on this drive-past.",
        )
        encoded = base64.b64encode(data).decode("ascii")
        sections.append(
            f"<figure><img alt='{html.escape(name)}' src='data:image/png;base64,{encoded}'>"
            f"<figcaption>{html.escape(name)}: {html.escape(caption)}</figcaption></figure>"
        )
    if not figures.png:
        sections.append("<p>No figures (the notes say why).</p>")
    notes_html = "".join(f"<li>{html.escape(n)}</li>" for n in notes)
    title = f"rsucal calibration report: {result.rsu_id} / {result.camera_id}"
    return f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>{html.escape(title)}</title>
<style>
body {{ font-family: sans-serif; max-width: 1000px; margin: 2em auto; color: #222; }}
table {{ border-collapse: collapse; }}
th, td {{ text-align: left; padding: 2px 10px; border-bottom: 1px solid #ddd; }}
.accepted {{ color: #1a7f37; font-weight: bold; }} .refused {{ color: #b42318; font-weight: bold; }}
figure {{ margin: 1.5em 0; }} img {{ max-width: 100%; }} figcaption {{ font-size: 0.9em; color: #555; }}
</style></head><body>
<h1>{html.escape(title)}</h1>
<h2>Verdict</h2>{_verdict_words(result)}
<h2>Result</h2>{_table(_facts(result))}
<h2>Figures</h2>{"".join(sections)}
{f"<h2>Notes</h2><ul>{notes_html}</ul>" if notes else ""}
</body></html>
"""


def write_report(
    result: CalibrationResult,
    outcome: CalibrationOutcome,
    vehicle: VehicleProfile,
    detections: Sequence[DetectionFrame],
    html_path: Path,
    png_dir: Path | None = None,
    notes: Sequence[str] = (),
    images: ImageSource | None = None,
) -> list[Path]:
    """Write the HTML report (and, with `png_dir`, each figure as a PNG); the paths written, HTML first."""
    figures = render_figures(result, outcome, vehicle, detections, images)
    html_path = Path(html_path)
    html_path.parent.mkdir(parents=True, exist_ok=True)
    written = [html_path]
    write_atomic(html_path, report_html(result, figures, notes).encode("utf-8"))  # never half a report
    if png_dir is not None:
        png_dir.mkdir(parents=True, exist_ok=True)
        for name, data in figures.png.items():
            path = png_dir / name
            path.write_bytes(data)
            written.append(path)
    return written


def write_report_failure(
    result: CalibrationResult, html_path: Path, reason: str, notes: Sequence[str] = ()
) -> Path:
    """The report page without figures, saying why they could not be drawn (the result is still there)."""
    text = report_html(result, Figures({}), [f"the figures could not be drawn: {reason}", *notes])
    write_atomic(html_path, text.encode("utf-8"))
    return html_path


# ---------------------------------------------------------------------------------------------- rsucal report


def _pose_difference(a: CalibrationResult, b: CalibrationResult) -> tuple[float, float] | None:
    """(shift m, angle deg) between two results' camera poses, or None when one has no pose."""
    if a.R is None or a.t is None or b.R is None or b.t is None or a.frame.crs != b.frame.crs:
        return None
    R_a, R_b = np.asarray(a.R, dtype=np.float64), np.asarray(b.R, dtype=np.float64)
    centre_a = camera_centre(R_a, np.asarray(a.t, dtype=np.float64)) + np.asarray(a.frame.origin)
    centre_b = camera_centre(R_b, np.asarray(b.t, dtype=np.float64)) + np.asarray(b.frame.origin)
    return pose_distance(R_a, centre_a, R_b, centre_b)


def run_report(
    result_path: Path,
    vehicle_path: Path,
    out_dir: Path,
    *,
    mcap_path: Path | None = None,
    detections_path: Path | None = None,
    poses_path: Path | None = None,
    station_id: int | None = None,
    time_offset_ns: int = 0,
    seed: int = 0,
    workers: int | None = None,
    max_v2x_std_m: float = DEFAULT_MAX_V2X_STD_M,
) -> list[Path]:
    """`rsucal report`: re-run calibrate() on the result's data and write report.html + PNGs to `out_dir`.

    The data is the result's camera (and, from an MCAP, its calibration vehicle: provenance.station_id
    unless `station_id` is given) in the result's UTM zone; intrinsics are the result's. InputError for a
    bad file or option (naming it).
    """
    from daemon.offline import load_offline_inputs
    from daemon.workers import track_pool
    from pipeline.calibrate import PipelineParams, calibrate
    from pipeline.loaders import load_calibration_result
    from schemas.common import LOCAL_CRS

    result = load_calibration_result(Path(result_path))
    loaded = load_offline_inputs(
        result.intrinsics,
        Path(vehicle_path),
        mcap_path=mcap_path,
        detections_path=detections_path,
        poses_path=poses_path,
        camera_id=result.camera_id,
        station_id=station_id if station_id is not None else result.provenance.station_id,
        # A result in a local metric frame (calibrate --frame local) is re-run in that frame.
        crs=None if result.frame.crs == LOCAL_CRS else result.frame.crs,
        frame="local" if result.frame.crs == LOCAL_CRS else "utm",
        time_offset_ns=time_offset_ns,
        max_v2x_std_m=max_v2x_std_m,
    )
    with track_pool(workers) as map_fn:
        outcome = calibrate(
            loaded.inputs,
            PipelineParams(),
            np.random.default_rng(seed),
            created_at_ns=time.time_ns(),
            map_fn=map_fn,
        )
    notes = list(loaded.notes)
    difference = _pose_difference(result, outcome.result)
    if difference is None:
        notes.append(
            f"the re-run on this data ({outcome.result.verdict.status}) has no pose to compare with the "
            "result's; the figures show the result's pose on the re-run's tracks"
        )
    else:
        shift_m, angle_deg = difference
        same = shift_m <= 0.01 and angle_deg <= 0.01
        notes.append(
            f"re-run on this data (seed {seed}): {outcome.result.verdict.status}, "
            f"{shift_m:.3f} m / {angle_deg:.3f} deg from the result"
            + (
                ""
                if same
                else ": not the same pose; the figures show the result's pose, the hypotheses the re-run's"
            )
        )
    notes.extend(
        f"{report.stage}: kept {report.kept}, discarded {report.discarded}" for report in outcome.stages
    )
    images: ImageSource | None = None
    if mcap_path is not None:
        from daemon.recording import read_images

        rsu_id, camera_id = loaded.inputs.rsu_id, loaded.inputs.camera_id
        files = [Path(mcap_path)]

        def images(stamps: Sequence[int]) -> Mapping[int, bytes]:
            return read_images(files, rsu_id, camera_id, stamps)

    return write_report(
        result,
        outcome,
        loaded.inputs.vehicle,
        loaded.inputs.detections,
        Path(out_dir) / "report.html",
        Path(out_dir),
        notes,
        images,
    )
