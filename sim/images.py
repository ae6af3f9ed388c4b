"""Camera images of a simulated scene: the vehicles' shaded body meshes over the preview's ground, roads and
occluders, as the RSU camera would have exposed them (OpenCV lens model, distortion included).

`render_images(result, camera_id, every)` yields (stamp_ns, BGR image) for every `every`-th frame: the
stamp is the detection frame's (exposure plus the camera's latency, as a camera pipeline stamps its
images). Bodies are drawn far to near and, within a body, face by face far to near (painter's algorithm),
lit by a fixed sun; occluders take part in the same order. The images feed foxglove.CompressedImage
channels (`rsucal simulate --images`), so a recording shows the scene and the image path can be tried.

`keyed=True` paints every vehicle (the calibration vehicle like any other) and its wheels in one of four
key colours (KEY_PAINTS: saturated red, blue, magenta, green, shaded like any paint) that nothing else in
the scene has, in turn by vehicle number (vehicles that follow each other mostly differ):
sim.key_detector's ONNX model finds vehicles by those colours, so `rsucal demo --images` can run the
daemon's image path without a trained detector (none ships with rsucal).
"""

from __future__ import annotations

import zlib
from collections.abc import Iterator

import cv2
import numpy as np

from sim.geometry import FloatArray, attitude_matrices, camera_position
from sim.lens import Lens
from sim.preview import _background, _draw_occluders, _draw_roads, _View
from sim.shapes import BodyShape
from sim.simulate import SimulationResult

SUN = np.array([0.35, -0.45, 0.82]) / np.linalg.norm([0.35, -0.45, 0.82])
AMBIENT = 0.35
WHEEL_BGR = (38, 38, 40)
# Paint colours of ordinary cars (BGR): white, silver, grey, black, blue, red, green, beige.
PAINTS = (
    (235, 235, 235),
    (192, 192, 188),
    (120, 120, 118),
    (40, 40, 42),
    (150, 80, 30),
    (40, 40, 170),
    (60, 110, 60),
    (150, 180, 200),
)
CALIBRATION_PAINT = (20, 140, 250)  # the calibration vehicle: orange, like its boxes in the recordings
# Key colours (BGR) of `keyed` images, sim.key_detector's classes 0-3: green near zero in the first three, red
# and blue in the last, which no sky, ground, road, marking or occluder colour of sim.preview comes close to;
# wheels get the body's key at KEY_WHEEL_SHADE.
KEY_PAINTS = ((0, 0, 255), (255, 0, 0), (255, 0, 255), (0, 255, 0))
KEY_WHEEL_SHADE = 0.5
_SUB = 4  # cv2 fixed-point drawing: 4 fractional bits


def _paint(vehicle: int, keyed: bool = False) -> tuple[int, int, int]:
    if keyed:  # the same rule for every vehicle: the key tells nothing about which is the calibration one
        return KEY_PAINTS[vehicle % len(KEY_PAINTS)]
    if vehicle == 0:
        return CALIBRATION_PAINT
    return PAINTS[zlib.crc32(vehicle.to_bytes(4, "little")) % len(PAINTS)]


def _shaded(colour: tuple[int, int, int], factor: float) -> tuple[int, int, int]:
    return round(colour[0] * factor), round(colour[1] * factor), round(colour[2] * factor)


def _draw_body(
    image: np.ndarray,
    view: _View,
    shape: BodyShape,
    pose: FloatArray,
    colour: tuple[int, int, int],
    wheel_colour: tuple[int, int, int] = WHEEL_BGR,
) -> None:
    """One vehicle's mesh, pose (6,) of its footprint centre; nothing if any vertex is behind the camera."""
    anchor = np.array([shape.length_m / 2.0, shape.width_m / 2.0, 0.0])
    R = attitude_matrices(pose[3:4], pose[4:5], pose[5:6])[0]
    world = (shape.vertices - anchor) @ R.T + pose[:3]
    cam = world @ view.R.T + view.t
    pixels, imageable = view.camera.project_cam(cam)
    if not np.all(imageable):  # behind the camera, or where the lens polynomial folds back: not drawn
        return
    faces = shape.faces
    tri = world[faces]  # (F, 3, 3)
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    length = np.linalg.norm(normal, axis=1)
    normal = normal / np.maximum(length, 1e-12)[:, None]
    centre = tri.mean(axis=1)
    facing = np.einsum("fi,fi->f", normal, camera_position(view.R, view.t) - centre) > 0.0
    light = AMBIENT + (1.0 - AMBIENT) * np.clip(normal @ SUN, 0.0, 1.0)
    depth = cam[faces].mean(axis=1)[:, 2]
    wheel = np.zeros(len(faces), dtype=bool)
    for part, (start, stop) in shape.parts.items():
        if part.startswith("wheel"):
            wheel |= np.any((faces >= start) & (faces < stop), axis=1)
    fixed = np.round(pixels * (1 << _SUB)).astype(np.int32)
    for f in np.argsort(-depth):
        if not facing[f] or length[f] <= 1e-12:
            continue
        base = wheel_colour if wheel[f] else colour
        shade = tuple(int(min(255.0, c * light[f])) for c in base)
        cv2.fillConvexPoly(image, fixed[faces[f]], shade, cv2.LINE_AA, _SUB)


def render_images(
    result: SimulationResult, camera_id: str, every: int = 1, keyed: bool = False
) -> Iterator[tuple[int, np.ndarray]]:
    """(detection stamp_ns, BGR uint8 image) of every `every`-th frame of one camera, first frame first;
    `keyed`: vehicles in KEY_PAINTS (module docstring)."""
    if every < 1:
        raise ValueError(f"every = {every} must be at least 1")
    camera = next(c for c in result.cameras if c.camera_id == camera_id)
    scene = result.scenes[camera_id]
    lens = Lens.from_intrinsics(camera.intrinsics)
    # The static part once: sky, ground and roads as the first extrinsic sees them (a moved camera's
    # background stays that of its first pose; the vehicles use the pose of their frame).
    view = _View(lens, camera.R_cam_from_local, camera.t_cam_from_local)
    ground_z = float(result.world.ground_height(camera_position(view.R, view.t)[None, :2])[0])
    static = _background(view, ground_z)
    _draw_roads(static, view, result.world.lanes)
    occluders = [(o.kind, np.asarray(o.corners, dtype=np.float64)) for o in result.world.occluders]
    centre = camera_position(view.R, view.t)
    occluder_distance = [float(np.hypot(*(c[:4, :2].mean(axis=0) - centre[:2]))) for _, c in occluders]
    order = np.argsort(scene.frame, kind="stable")
    frames, poses, vehicles = scene.frame[order], scene.poses[order], scene.vehicle[order]
    bounds = np.searchsorted(frames, np.arange(len(result.detections[camera_id]) + 1))
    for index, detection in enumerate(result.detections[camera_id]):
        if index % every:
            continue
        image = static.copy()
        rows = range(int(bounds[index]), int(bounds[index + 1]))
        things: list[tuple[float, int, int]] = [
            (float(np.hypot(*(poses[r, :2] - centre[:2]))), 0, r) for r in rows
        ]
        things += [(d, 1, k) for k, d in enumerate(occluder_distance)]
        for _, kind, item in sorted(things, reverse=True):
            if kind == 1:
                _draw_occluders(image, view, [occluders[item]])
            else:
                vehicle = int(vehicles[item])
                paint = _paint(vehicle, keyed)
                wheels = _shaded(paint, KEY_WHEEL_SHADE) if keyed else WHEEL_BGR
                _draw_body(image, view, result.bodies[vehicle], poses[item], paint, wheels)
        yield detection.stamp_ns, image
