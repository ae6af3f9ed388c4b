"""A picture of one simulated frame as the RSU camera would see it, for `rsucal simulate --preview`.

Input: a SimulationResult (true extrinsic, world geometry, detections, ground truth). Output: a BGR uint8
image of the camera's resolution: flat-shaded ground and sky, roads around the lane centre lines,
occluders, every detected box of the busiest frame in which the calibration vehicle is detected, that
vehicle's box highlighted and its true footprint, and a legend. Everything 3D goes through the camera's
distortion model, so straight road edges bend exactly as they would in the real image.
"""

from __future__ import annotations

import datetime as dt
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np

from schemas.files import GroundTruthFrame
from schemas.messages import DetectionFrame
from sim.errors import SimulationError
from sim.geometry import BoolArray, FloatArray, camera_position
from sim.lens import Lens

if TYPE_CHECKING:
    from sim.simulate import SimulatedCamera, SimulationResult

Mask = BoolArray
Pixels = FloatArray
Points3 = FloatArray
# A box edge this close to the image border (px) was cut by it: the vehicle is not seen whole.
BORDER_MARGIN_PX = 3.0

Color = tuple[int, int, int]

# BGR. The highlight is used for nothing else, so a test (or an eye) can find the calibration vehicle.
HIGHLIGHT_BGR: Color = (255, 0, 255)
FOOTPRINT_BGR: Color = (0, 255, 0)
OTHER_BOX_BGR: Color = (255, 190, 40)
OUTLINE_BGR: Color = (40, 220, 255)
INSET_RANGE_M = 150.0
LANE_CENTRE_BGR: Color = (0, 200, 255)
JUNCTION_CENTRE_BGR: Color = (60, 130, 150)
ROAD_EDGE_BGR: Color = (225, 225, 225)
ASPHALT_BGR: Color = (88, 86, 84)
GRASS_BGR: Color = (58, 92, 66)
HAZE_BGR: Color = (175, 170, 160)
SKY_HORIZON_BGR: Color = (200, 180, 160)
SKY_ZENITH_BGR: Color = (120, 70, 40)
OCCLUDER_BGR: dict[str, Color] = {"crown": (60, 125, 70), "trunk": (45, 75, 110), "pole": (125, 125, 125)}
OTHER_OCCLUDER_BGR: Color = (110, 120, 115)

LANE_WIDTH_M = 3.5
SAMPLE_STEP_M = 0.5  # lanes and footprints are sampled this densely so distortion bends them correctly
HAZE_DISTANCE_M = 300.0
_SUB = 4  # cv2 drawing with 4 fractional bits: sub-pixel positions without float support in cv2
_BOX_FACES = ((0, 1, 2, 3), (4, 5, 6, 7), (0, 1, 5, 4), (1, 2, 6, 5), (2, 3, 7, 6), (3, 0, 4, 7))


class _View:
    """One camera's projection, restricted to where its distortion model is valid.

    The polynomial lens model folds back far outside the image (a point 3x beyond the border can land
    inside it), so points whose undistorted direction lies beyond the image's own field of view (+20 %)
    are treated as invisible instead of being drawn at a wrong place.
    """

    def __init__(self, camera: Lens, R: FloatArray, t: FloatArray) -> None:
        self.camera, self.R, self.t = camera, R, t
        w, h = camera.width, camera.height
        border = np.array(
            [[0, 0], [w / 2, 0], [w, 0], [w, h / 2], [w, h], [w / 2, h], [0, h], [0, h / 2]], dtype=np.float64
        )
        xy = camera.undistort(border)
        self.max_x = 1.2 * float(np.max(np.abs(xy[:, 0])))
        self.max_y = 1.2 * float(np.max(np.abs(xy[:, 1])))

    def project(self, points: Points3) -> tuple[Pixels, Mask, FloatArray]:
        """Local points (N, 3) -> pixels (N, 2), visibility (N,), depth (N,) m."""
        points_cam = points @ self.R.T + self.t
        depth = points_cam[:, 2]
        pixels = np.full((len(points), 2), np.nan)
        front = depth > 1e-9
        if np.any(front):
            projected, _ = cv2.projectPoints(
                points_cam[front], np.zeros(3), np.zeros(3), self.camera.K, self.camera.dist
            )
            pixels[front] = projected.reshape(-1, 2)
        with np.errstate(divide="ignore", invalid="ignore"):
            x = points_cam[:, 0] / points_cam[:, 2]
            y = points_cam[:, 1] / points_cam[:, 2]
        visible = (depth > 0.1) & (np.abs(x) <= self.max_x) & (np.abs(y) <= self.max_y)
        return pixels, np.asarray(visible, dtype=np.bool_), depth


def _fixed(pixels: Pixels) -> np.ndarray:
    return np.round(pixels * (1 << _SUB)).astype(np.int32)


def _runs(mask: Mask) -> list[tuple[int, int]]:
    """[start, stop) index ranges of consecutive True values."""
    padded = np.concatenate([[False], mask, [False]]).astype(np.int8)
    edges = np.flatnonzero(np.diff(padded))
    return [(int(a), int(b)) for a, b in zip(edges[::2], edges[1::2], strict=True)]


def _draw_polyline(image: np.ndarray, pixels: Pixels, visible: Mask, color: Color, thickness: int) -> None:
    """Draw the visible stretches of a polyline; a gap where it leaves the view (or goes behind us)."""
    pieces = [_fixed(pixels[a:b]) for a, b in _runs(visible) if b - a >= 2]
    if pieces:
        cv2.polylines(image, pieces, False, color, thickness, cv2.LINE_AA, _SUB)


def _resample(polyline: FloatArray, step_m: float) -> FloatArray:
    """Points every `step_m` metres along a (K, 3) polyline, keeping its end points."""
    seg = np.linalg.norm(np.diff(polyline, axis=0), axis=1)
    arc = np.concatenate([[0.0], np.cumsum(seg)])
    if arc[-1] <= 0.0:
        return polyline[:1].copy()
    s = np.linspace(0.0, arc[-1], max(2, int(np.ceil(arc[-1] / step_m)) + 1))
    return np.column_stack([np.interp(s, arc, polyline[:, k]) for k in range(3)])


def _background(view: _View, ground_z: float) -> np.ndarray:
    """Sky above the horizon, grass below it fading into haze with distance (on a coarse grid, upscaled)."""
    cam = view.camera
    step = 4
    u = (np.arange(0, cam.width, step) + step / 2).astype(np.float64)
    v = (np.arange(0, cam.height, step) + step / 2).astype(np.float64)
    uu, vv = np.meshgrid(u, v)
    xy = cam.undistort(np.column_stack([uu.ravel(), vv.ravel()]))
    rays = np.column_stack([xy, np.ones(len(xy))]) @ view.R  # local-frame directions
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    centre = camera_position(view.R, view.t)
    down = -rays[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        distance = np.where(down > 1e-6, (centre[2] - ground_z) / down, np.inf)
    haze = 1.0 - np.exp(-distance / HAZE_DISTANCE_M)
    ground = (1.0 - haze)[:, None] * np.array(GRASS_BGR) + haze[:, None] * np.array(HAZE_BGR)
    elevation = np.clip(rays[:, 2], 0.0, 1.0) ** 0.5
    sky = (1.0 - elevation)[:, None] * np.array(SKY_HORIZON_BGR) + elevation[:, None] * np.array(
        SKY_ZENITH_BGR
    )
    colour = np.where((down > 1e-6)[:, None], ground, sky).reshape(len(v), len(u), 3)
    small = np.clip(colour, 0, 255).astype(np.uint8)
    return np.asarray(cv2.resize(small, (cam.width, cam.height), interpolation=cv2.INTER_LINEAR))


def _junction_lanes(lanes: Sequence[FloatArray], tolerance_m: float = 0.5) -> Mask:
    """Lanes that join two other lanes at both ends: the turning paths through a junction.

    The world only gives centre lines; a connector starts where an inbound lane ends and ends where an
    outbound lane starts, while an arm's lane has one free end far out. Connectors get asphalt but no
    edge markings, as on a real junction.
    """
    ends = np.array([[lane[0, :2], lane[-1, :2]] for lane in lanes]).reshape(-1, 2, 2)
    is_connector = np.zeros(len(lanes), dtype=np.bool_)
    for i in range(len(lanes)):
        others = np.delete(ends, i, axis=0).reshape(-1, 2)
        if len(others) == 0:
            continue
        gap = np.linalg.norm(ends[i][:, None, :] - others[None, :, :], axis=2).min(axis=1)
        is_connector[i] = bool(np.all(gap < tolerance_m))
    return is_connector


def _lane_width(lanes: Sequence[FloatArray], connector: Mask) -> float:
    """Lane spacing (m) from the lanes themselves: the median distance from each arm lane's middle point to
    the nearest other arm lane (the world gives centre lines only); LANE_WIDTH_M when implausible."""
    arms = [lane[:, :2] for lane, is_connector in zip(lanes, connector, strict=True) if not is_connector]
    if len(arms) < 2:
        return LANE_WIDTH_M
    gaps = []
    for i, lane in enumerate(arms):
        middle = lane[len(lane) // 2]
        others = np.vstack([other for j, other in enumerate(arms) if j != i])
        gaps.append(float(np.min(np.linalg.norm(others - middle, axis=1))))
    width = float(np.median(gaps))
    return width if 2.5 <= width <= 5.0 else LANE_WIDTH_M


def _draw_roads(image: np.ndarray, view: _View, lanes: Sequence[FloatArray]) -> None:
    """Asphalt band one lane wide around each lane centre, white edges, a dashed centre line (the lane
    polylines themselves; faint inside the junction)."""
    sampled = [_resample(np.asarray(lane, dtype=np.float64), SAMPLE_STEP_M) for lane in lanes]
    sampled = [lane for lane in sampled if len(lane) >= 2]
    if not sampled:
        return
    connector = _junction_lanes(sampled)
    half_width = _lane_width(sampled, connector) / 2.0
    sides = []
    for lane in sampled:
        tangent = np.gradient(lane[:, :2], axis=0)
        tangent /= np.maximum(np.linalg.norm(tangent, axis=1, keepdims=True), 1e-9)
        left = np.column_stack([-tangent[:, 1], tangent[:, 0], np.zeros(len(lane))])
        sides.append((lane + left * half_width, lane - left * half_width))
    # All asphalt first, so one lane's band never covers another lane's markings.
    for left_edge, right_edge in sides:
        lp, lv, _ = view.project(left_edge)
        rp, rv, _ = view.project(right_edge)
        ok = lv[:-1] & lv[1:] & rv[:-1] & rv[1:]
        quads = np.stack([lp[:-1], lp[1:], rp[1:], rp[:-1]], axis=1)[ok]
        if len(quads):
            cv2.fillPoly(image, list(_fixed(quads)), ASPHALT_BGR, cv2.LINE_AA, _SUB)
    for (left_edge, right_edge), lane, in_junction in zip(sides, sampled, connector, strict=True):
        if not in_junction:
            for edge in (left_edge, right_edge):
                pixels, visible, _ = view.project(edge)
                _draw_polyline(image, pixels, visible, ROAD_EDGE_BGR, 1)
        pixels, visible, _ = view.project(lane)
        dashes = (np.arange(len(lane)) // 6) % 2 == 0  # 3 m dash, 3 m gap
        colour = JUNCTION_CENTRE_BGR if in_junction else LANE_CENTRE_BGR
        _draw_polyline(image, pixels, visible & dashes, colour, 1)


def _scaled(colour: Color, factor: float) -> Color:
    return (int(colour[0] * factor), int(colour[1] * factor), int(colour[2] * factor))


def _draw_occluders(image: np.ndarray, view: _View, occluders: Sequence[tuple[str, FloatArray]]) -> None:
    """Flat-shaded faces of box-shaped occluders (kind, 8 corners: 4 bottom then 4 top), far faces first."""
    centre = camera_position(view.R, view.t)
    light = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    faces: list[tuple[float, np.ndarray, Color]] = []
    fraction = np.linspace(0.0, 1.0, 17)[:-1]
    for kind, corners in occluders:
        base = OCCLUDER_BGR.get(kind, OTHER_OCCLUDER_BGR)
        body_centre = corners.mean(axis=0)
        for face in _BOX_FACES:
            quad = corners[list(face)]
            face_centre = quad.mean(axis=0)
            normal = np.cross(quad[1] - quad[0], quad[3] - quad[0])
            if np.linalg.norm(normal) < 1e-9:
                continue
            normal /= np.linalg.norm(normal)
            if normal @ (face_centre - body_centre) < 0:
                normal = -normal
            if normal @ (centre - face_centre) <= 0:
                continue  # facing away from the camera
            # Dense outline, so a face bends with the lens and can be cut where it leaves the view.
            outline = np.concatenate(
                [quad[k] + fraction[:, None] * (quad[(k + 1) % 4] - quad[k]) for k in range(4)]
            )
            pixels, visible, depth = view.project(outline)
            if np.count_nonzero(visible) < 3:
                continue
            shade = 0.55 + 0.45 * max(0.0, float(normal @ light))
            faces.append((float(np.mean(depth[visible])), pixels[visible], _scaled(base, shade)))
    for _, pixels, colour in sorted(faces, key=lambda item: -item[0]):
        polygon = _fixed(pixels)
        cv2.fillPoly(image, [polygon], colour, cv2.LINE_AA, _SUB)
        cv2.polylines(image, [polygon], True, _scaled(colour, 0.6), 1, cv2.LINE_AA, _SUB)


def _draw_boxes(image: np.ndarray, frame: DetectionFrame, calib_index: int | None) -> None:
    """Every detection of the frame: translucent fill and outline; the calibration vehicle in HIGHLIGHT."""
    overlay = image.copy()
    for index, box in enumerate(frame.boxes):
        if index != calib_index:
            p1 = (round(box.x1 * (1 << _SUB)), round(box.y1 * (1 << _SUB)))
            p2 = (round(box.x2 * (1 << _SUB)), round(box.y2 * (1 << _SUB)))
            cv2.rectangle(overlay, p1, p2, OTHER_BOX_BGR, -1, cv2.LINE_AA, _SUB)
    cv2.addWeighted(overlay, 0.18, image, 0.82, 0.0, dst=image)
    for index, box in enumerate(frame.boxes):
        if index == calib_index:
            continue
        p1 = (round(box.x1 * (1 << _SUB)), round(box.y1 * (1 << _SUB)))
        p2 = (round(box.x2 * (1 << _SUB)), round(box.y2 * (1 << _SUB)))
        cv2.rectangle(image, p1, p2, OTHER_BOX_BGR, 1, cv2.LINE_AA, _SUB)
    if calib_index is not None and calib_index < len(frame.boxes):
        box = frame.boxes[calib_index]
        # Integer corners without anti-aliasing: the highlight's exact colour survives in the image.
        cv2.rectangle(image, (round(box.x1), round(box.y1)), (round(box.x2), round(box.y2)), HIGHLIGHT_BGR, 2)


def _draw_footprint(image: np.ndarray, view: _View, footprint: FloatArray) -> None:
    """The calibration vehicle's true footprint (4, 3), edges sampled densely, corners marked."""
    closed = np.vstack([footprint, footprint[:1]])
    fraction = np.linspace(0.0, 1.0, 21)
    outline = np.concatenate([closed[k] + fraction[:, None] * (closed[k + 1] - closed[k]) for k in range(4)])
    pixels, visible, _ = view.project(outline)
    _draw_polyline(image, pixels, visible, FOOTPRINT_BGR, 1)
    corner_pixels, corner_visible, _ = view.project(footprint)
    for pixel in corner_pixels[corner_visible]:
        cv2.circle(
            image,
            tuple(int(c) for c in _fixed(pixel[None])[0]),
            4 << _SUB,
            FOOTPRINT_BGR,
            -1,
            cv2.LINE_AA,
            _SUB,
        )


def _body_world_points(footprint: FloatArray, body: FloatArray) -> FloatArray:
    """Body vertices (K, 3) about the footprint centre -> local frame, with the attitude the true footprint
    (4, 3: rear-right, front-right, front-left, rear-left) shows."""
    forward = footprint[1] - footprint[0]
    left = footprint[3] - footprint[0]
    x = forward / np.linalg.norm(forward)
    y = left - x * float(left @ x)
    y /= np.linalg.norm(y)
    z = np.cross(x, y)
    centre = footprint.mean(axis=0)
    return np.asarray(centre + body @ np.stack([x, y, z]), dtype=np.float64)


def _draw_outline(image: np.ndarray, view: _View, footprint: FloatArray, body: FloatArray) -> None:
    """The calibration vehicle's true silhouette (the hull of its projected body), translucent, with its
    edge: what the detector's box should bound."""
    pixels, visible, _ = view.project(_body_world_points(footprint, body))
    if int(visible.sum()) < 3:
        return
    hull = cv2.convexHull(_fixed(pixels[visible]).astype(np.int32))
    overlay = image.copy()
    cv2.fillConvexPoly(overlay, hull, OUTLINE_BGR, cv2.LINE_AA, _SUB)
    cv2.addWeighted(overlay, 0.35, image, 0.65, 0.0, dst=image)
    cv2.polylines(image, [hull], True, OUTLINE_BGR, 1, cv2.LINE_AA, _SUB)


def _draw_inset(image: np.ndarray, result: SimulationResult, view: _View, focus: FloatArray | None) -> None:
    """A top-down map in the bottom-right corner: lanes, the camera and the ground its image covers (up to
    INSET_RANGE_M away), the calibration vehicle's true path and, if given, where it is in this frame."""
    size = int(min(image.shape[0], image.shape[1]) * 0.36)
    margin = 8
    x0, y0 = image.shape[1] - size - margin, image.shape[0] - size - margin
    panel = image[y0 : y0 + size, x0 : x0 + size]
    panel[:] = (panel * 0.25 + 18).astype(np.uint8)
    centre_cam = camera_position(view.R, view.t)
    # Ground covered by the image: rays through the border, cut at the ground below the camera.
    border = view.camera.undistort(view.camera.border_pixels(16))
    rays = np.column_stack([border, np.ones(len(border))]) @ view.R
    ground_z = float(result.world.ground_height(centre_cam[None, :2])[0])
    down = -rays[:, 2]
    reach = np.where(down > 1e-6, (centre_cam[2] - ground_z) / np.maximum(down, 1e-6), np.inf)
    reach = np.minimum(reach, INSET_RANGE_M / np.maximum(np.hypot(rays[:, 0], rays[:, 1]), 1e-9))
    covered = centre_cam[:2] + rays[:, :2] * reach[:, None]
    span = np.concatenate([covered, centre_cam[None, :2]])
    lo, hi = span.min(axis=0) - 15.0, span.max(axis=0) + 15.0
    scale = (size - 2 * margin) / float(max(hi - lo))
    mid = 0.5 * (lo + hi)

    def to_px(xy: FloatArray) -> np.ndarray:
        u = size / 2 + (xy[:, 0] - mid[0]) * scale
        v = size / 2 - (xy[:, 1] - mid[1]) * scale  # north up
        return np.round(np.column_stack([u, v]) * (1 << _SUB)).astype(np.int32)

    cv2.fillPoly(panel, [to_px(covered)], (60, 70, 60), cv2.LINE_AA, _SUB)
    for lane in result.world.lanes:
        cv2.polylines(panel, [to_px(lane[:, :2])], False, LANE_CENTRE_BGR, 1, cv2.LINE_AA, _SUB)
    path = result.true_poses[:, :2]
    cv2.polylines(panel, [to_px(path)], False, HIGHLIGHT_BGR, 1, cv2.LINE_AA, _SUB)
    cv2.circle(
        panel,
        tuple(int(c) for c in to_px(centre_cam[None, :2])[0]),
        5 << _SUB,
        (255, 255, 255),
        -1,
        cv2.LINE_AA,
        _SUB,
    )
    if focus is not None:
        cv2.polylines(panel, [to_px(focus[:, :2])], True, FOOTPRINT_BGR, 2, cv2.LINE_AA, _SUB)
    cv2.rectangle(panel, (0, 0), (size - 1, size - 1), (200, 200, 200), 1)
    cv2.putText(
        panel, "N^  top-down", (6, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (230, 230, 230), 1, cv2.LINE_AA
    )


def _draw_legend(image: np.ndarray, lines: Sequence[str], keys: Sequence[tuple[Color, str]]) -> None:
    """Text panel in the top-left corner, scaled with the image width."""
    scale = max(0.4, image.shape[1] / 2400.0)
    line_h = int(26 * scale / 0.8)
    rows = len(lines) + len(keys)
    width = int(min(image.shape[1] - 10, 900 * scale / 0.8))
    panel = image[5 : 5 + line_h * rows + 12, 5 : 5 + width]
    panel[:] = (panel * 0.35).astype(np.uint8)
    y = 5 + line_h
    for text in lines:
        cv2.putText(image, text, (14, y), cv2.FONT_HERSHEY_SIMPLEX, scale, (240, 240, 240), 1, cv2.LINE_AA)
        y += line_h
    for colour, text in keys:
        cv2.rectangle(image, (14, y - line_h // 2 - 2), (14 + line_h, y - 2), colour, 2)
        cv2.putText(
            image, text, (24 + line_h, y), cv2.FONT_HERSHEY_SIMPLEX, scale, (240, 240, 240), 1, cv2.LINE_AA
        )
        y += line_h


def _select_camera(result: SimulationResult, camera_id: str | None) -> SimulatedCamera:
    if not result.cameras:
        raise SimulationError("simulation", "no cameras to preview")
    if camera_id is None:
        return result.cameras[0]
    for camera in result.cameras:
        if camera.camera_id == camera_id:
            return camera
    known = ", ".join(c.camera_id for c in result.cameras)
    raise SimulationError("camera_id", f"camera_id = {camera_id!r} not in the simulation ({known})")


def busiest_calib_frame(
    frames: Sequence[DetectionFrame], truth_frames: Sequence[GroundTruthFrame], width: int, height: int
) -> tuple[int | None, GroundTruthFrame | None]:
    """Index of the frame with the most boxes among those where the calibration vehicle is detected
    (on ties: its box inside the width x height image, then largest), and its truth; the busiest frame of
    all (truth None) when it never is."""
    if not frames:
        return None, None
    truth_by_stamp = {t.stamp_ns: t for t in truth_frames}
    with_calib = [
        i
        for i, f in enumerate(frames)
        if (t := truth_by_stamp.get(f.stamp_ns)) is not None and t.calib_box is not None
    ]

    def calib_view(i: int) -> tuple[bool, float]:
        row = truth_by_stamp[frames[i].stamp_ns].calib_box
        if row is None or row >= len(frames[i].boxes):
            return False, 0.0
        box = frames[i].boxes[row]
        m = BORDER_MARGIN_PX
        inside = box.x1 > m and box.y1 > m and box.x2 < width - m and box.y2 < height - m
        return bool(inside), (box.x2 - box.x1) * (box.y2 - box.y1)

    if not with_calib:
        return max(range(len(frames)), key=lambda i: (len(frames[i].boxes), -i)), None
    # Among equally busy frames, the one showing the calibration vehicle whole and largest shows it best.
    best = max(with_calib, key=lambda i: (len(frames[i].boxes), *calib_view(i), -i))
    return best, truth_by_stamp[frames[best].stamp_ns]


def render_preview(result: SimulationResult, camera_id: str | None = None) -> np.ndarray:
    """BGR uint8 image (height, width, 3) of one simulated camera (the first one by default) at the busiest
    frame in which the calibration vehicle is detected, drawn with the true extrinsic and distortion."""
    sim_camera = _select_camera(result, camera_id)
    camera = Lens.from_intrinsics(sim_camera.intrinsics)
    R = np.asarray(sim_camera.R_cam_from_local, dtype=np.float64)
    t = np.asarray(sim_camera.t_cam_from_local, dtype=np.float64)
    view = _View(camera, R, t)

    centre = camera_position(R, t)
    ground_z = float(result.world.ground_height(centre[None, :2])[0])
    image = _background(view, ground_z)
    _draw_roads(image, view, result.world.lanes)
    _draw_occluders(
        image, view, [(o.kind, np.asarray(o.corners, dtype=np.float64)) for o in result.world.occluders]
    )

    frames = result.detections.get(sim_camera.camera_id, [])
    truth = result.ground_truth.get(sim_camera.camera_id)
    index, truth_frame = busiest_calib_frame(
        frames, truth.frames if truth is not None else [], camera.width, camera.height
    )
    lines = [f"rsucal simulation  preset {result.preset}  seed {result.seed}  rsu {result.rsu_id}"]
    if index is None:
        lines.append(f"camera {sim_camera.camera_id}: no detection frames")
    else:
        frame = frames[index]
        calib_index = truth_frame.calib_box if truth_frame is not None else None
        if truth_frame is not None and truth_frame.footprint_local is not None:
            footprint = np.asarray(truth_frame.footprint_local, dtype=np.float64)
            body = result.bodies[0]  # the calibration vehicle's, about its footprint centre:
            vertices = body.vertices - np.array([body.length_m / 2.0, body.width_m / 2.0, 0.0])
            _draw_outline(image, view, footprint, vertices)
        _draw_boxes(image, frame, calib_index)
        # On top of the highlight: on a distant vehicle the footprint is only a few pixels across.
        if truth_frame is not None and truth_frame.footprint_local is not None:
            _draw_footprint(image, view, np.asarray(truth_frame.footprint_local, dtype=np.float64))
        when = dt.datetime.fromtimestamp(frame.stamp_ns / 1e9, tz=dt.UTC).isoformat(timespec="milliseconds")
        lines.append(
            f"camera {sim_camera.camera_id}  {camera.width}x{camera.height}  frame {index + 1}/{len(frames)}"
        )
        lines.append(f"stamp {frame.stamp_ns} ns  ({when})")
        status = (
            "calibration vehicle detected" if calib_index is not None else "calibration vehicle NOT detected"
        )
        lines.append(
            f"{len(frame.boxes)} boxes in this frame, {status}; {result.traffic_count} other vehicles"
        )
    focus = (
        np.asarray(truth_frame.footprint_local, dtype=np.float64)
        if truth_frame is not None and truth_frame.footprint_local is not None
        else None
    )
    _draw_inset(image, result, view, focus)
    world = (
        "ideal world"
        if result.is_ideal
        else f"real world, latency {truth.latency_ns / 1e6:.0f} ms"
        if truth
        else ""
    )
    lines.append(f"{world}; calibration vehicle: {truth.vehicle_type if truth else '?'}")
    keys = [
        (HIGHLIGHT_BGR, f"calibration vehicle box (station {result.station_id})"),
        (OUTLINE_BGR, "its true outline"),
        (FOOTPRINT_BGR, "its true footprint (data sheet)"),
        (OTHER_BOX_BGR, "other detections"),
        (LANE_CENTRE_BGR, "lane centre lines"),
    ]
    _draw_legend(image, lines, keys)
    return image


def write_previews(result: SimulationResult, path: Path) -> list[Path]:
    """One preview per camera: `path` itself for a single camera, PATH_<camera><suffix> for several."""
    path = Path(path)
    if len(result.cameras) <= 1:
        return [write_preview(result, path)]
    return [
        write_preview(result, path.with_name(f"{path.stem}_{c.camera_id}{path.suffix}"), c.camera_id)
        for c in result.cameras
    ]


def write_preview(result: SimulationResult, path: Path, camera_id: str | None = None) -> Path:
    """Render `render_preview` and write it as an image (format from the suffix, e.g. .png); returns path."""
    image = render_preview(result, camera_id)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), image):
        raise SimulationError(
            str(path), "could not write the preview image (unknown suffix or unwritable path)"
        )
    return path
