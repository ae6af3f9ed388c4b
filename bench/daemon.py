"""Daemon load benchmark (issue 4): ingest throughput with MCAP logging, memory over a simulated day, and the
time from the end of the quiet period to the calibration on the bus. Not part of the test suite.

    python -m bench.daemon [--part sustained|ceiling|rss|latency|detector|profile|reverify|all]
                           [--json out.json]

The mix: 4 cameras at 10 fps with 30 boxes per frame (the sil-west simulator's detector boxes, each frame
filled up with boxes of the camera's later frames, so coordinates and JSON sizes are a detector's: ~4 kB)
and one calibration vehicle's V2X at 50 Hz (~0.3 kB), driving a figure-eight at 15 m/s whose northern loop
passes the four cameras' coverage, so traversals are counted as in the field: 90 messages/s. The publisher
is a separate process with its own Zenoh session and congestion control BLOCK: a message lost is lost in the
daemon (its inbox), never dropped by the publisher.

  sustained  `rsucal daemon` itself (the CLI, its own process, a real Zenoh peer on a free loopback port,
             MCAP logging on) fed the mix in real time for --seconds: messages published, received, accepted,
             dropped, rejected; inbox depth over time; CPU of the daemon process; MCAP bytes/s and messages.
  ceiling    the same daemon, the mix time-compressed (stamps keep their spacing, so V2X stays plausible)
             and published at each of --rates messages/s for --step-s, Foxglove views recorded beside the
             raw channels as in the field (--no-foxglove-views: raw channels only, to compare). A rate
             passes when every message is accepted (none dropped or rejected) and the daemon kept up:
             published / (step + time until the inbox was empty again) >= 95 % of the rate. The bounded
             inbox (ingest.queue_size, 200,000) could absorb a whole 10 s burst, so the drain time is part
             of the criterion. Then one unpaced step.
  rss        a Daemon in this process on a ScaledClock, --rss-hours (24) simulated at --rss-rate x, fed
             through Zenoh by the publisher process at the scaled stamps. Detection and V2X rates are divided
             by --rss-divisor (5: 2 fps and 10 Hz; message sizes kept) so a day fits in minutes. Rotation
             every 30 min or 4 MiB, retention 4 h (pruning), the vehicle passes one camera 4 times every 8 h
             (jobs start and are refused: the boxes are not of that vehicle), health and status queried over
             Zenoh every simulated 5 min, RSS and live Python blocks sampled every simulated hour;
             --tracemalloc also lists the lines whose allocations grew (slower: lower --rss-rate with it).
  latency    the `long` preset replayed at --latency-rate x into a Daemon (ScaledClock, quiet_period_s 30,
             jobs.track_workers 2); per job: from the end of the quiet period (the tracker's last leave on our
             clock + quiet_period_s, in wall time) to the job's start and to its CalibrationResult arriving
             at a subscriber in another session.
  detector   the image path (not in `all`): a Daemon in this process with --detector-cameras cameras, each
             running an ONNX detector (1 onnxruntime thread, queue of 2), fed 1920 x 1080 JPEGs
             (foxglove.CompressedImage) at --detector-fps per camera over Zenoh for --seconds; detector frames
             per second per camera, images dropped, and the per-image cost of each stage in one thread. The
             model is the test suite's cell detector (tests/daemon/onnx_models.py, YOLOv8 layout, 640 x 640)
             behind a random-weight 3x3 convolution stack of 5.3 GFLOPs (YOLOv8n: 8.7): a network's arithmetic
             without weights, since none may be downloaded. A real detector's speed scales with its FLOPs.
  profile    (not in `all`) where the ingest time goes at --profile-rate messages/s: cProfile of a Daemon's
             ingest thread, the bus callback's cost, and (when py-spy is installed) py-spy of `rsucal daemon`,
             all threads and only the one holding the GIL.
  reverify   re-verifications of a static camera (issue 10 part 7): the moved-camera scene without its move,
             --reverify-seeds seeds (20), in the ideal world unless --reverify-real; per seed the daemon's job
             (run_job, in this process) on drive-pasts 1-4, then on 5-8 alone, the second judged against the
             first by daemon.publication.decide: shift, its std and limit, and whether a move was flagged.
Targets: ceiling >= 20,000 messages/s with zero loss; RSS at the end within 10 % of RSS after the first
simulated hour; quiet-period end -> calibration on the bus <= 10 s; no move flagged on a static camera.
Exit 1 when one fails.
"""

from __future__ import annotations

import argparse
import contextlib
import cProfile
import io
import json
import logging
import math
import multiprocessing
import os
import pstats
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field, replace
from multiprocessing.connection import Connection
from pathlib import Path
from typing import TYPE_CHECKING, Any

from bench.common import REPO_ROOT, load_average, process_usage, tree_state

if TYPE_CHECKING:
    import zenoh

    from daemon.main import Daemon
    from schemas.common import CameraIntrinsics, VehicleProfile
    from schemas.config import DaemonConfig, JobsConfig, StorageConfig, TriggerConfig
    from schemas.results import Health

CEILING_TARGET_MSGS_S = 20_000.0
RSS_GROWTH_LIMIT = 0.10
LATENCY_TARGET_S = 10.0

DEFAULT_RATES = (5_000, 10_000, 15_000, 20_000, 25_000, 30_000)
# A step passes when the publisher reached this share of the rate and the daemon processed this share of it
# over the step plus its drain (pacing in batches and the health round trip leave a few percent of jitter).
PUBLISHED_SHARE = 0.97
PROCESSED_SHARE = 0.95
DRAIN_TIMEOUT_S = 20.0  # give up waiting for the inbox to empty (the step has failed by then anyway)
FAILED_STEPS_BEFORE_SKIP = 2  # consecutive failed rates after which higher ones are not tried

SOURCE_PRESET = "sil-west"  # whose detector boxes fill the frames
TEMPLATE_FRAMES = 300  # distinct frames per camera, cycled (30 s at 10 fps)
CAMERA_PHASE_NS = 7_000_000  # cameras expose 7 ms apart (not synchronised with each other or the V2X)
STAMP_SENTINEL = 1_111_111_111_111_111_111  # placeholder in the JSON templates, replaced by each stamp
STATION_ID = 4242
ROUTE_RADIUS_M = 400.0  # each loop of the figure-eight
ROUTE_SPEED_MPS = 15.0
CAMERA_SPREAD_M = 20.0  # the 4 cameras stand around the junction at the top of loop A
COVERAGE_RADIUS_M = 80.0
OFF_ROUTE_M = 200.0
RSU_ID = "bench-rsu"
THROUGHPUT_PATTERN = "A"  # every loop passes the cameras
# rss: one camera on the route; 4 loops past it then 168 away (8 h at 168 s a loop): a job after the 3rd
# pass, three times a day (at 480x the 4th pass falls while that job runs, and its traversals age out of
# max_window_s before it ends). A job's CPU time is wall time, so more jobs would crowd a day's worth of
# calibrations into minutes (one job on these boxes takes ~10-20 s).
RSS_PATTERN = "AAAA" + "B" * 168
RSS_PASSED_CAMERAS = 1
RSS_START_NS = 1_717_200_000_000_000_000  # 2024-06-01 00:00 UTC
RSS_QUERY_EVERY_S = 300.0  # simulated
MIB = 1024 * 1024
GIB = 1024 * MIB
MATCH_TIMEOUT_S = 20.0
HEALTH_TIMEOUT_S = 5.0

# ------------------------------------------------------------------------------------------ the message mix


@dataclass(frozen=True, slots=True)
class Mix:
    """Messages per second: `cameras` x `fps` detection frames of `boxes` boxes, plus V2X at `v2x_hz`."""

    cameras: int = 4
    fps: int = 10
    boxes: int = 30
    v2x_hz: int = 50

    @property
    def messages_per_s(self) -> int:
        return self.cameras * self.fps + self.v2x_hz

    def divided(self, divisor: int) -> Mix:
        """The same cameras and message sizes at 1/divisor of the message rates."""
        if self.fps % divisor or self.v2x_hz % divisor:
            raise ValueError(f"--rss-divisor {divisor} must divide fps {self.fps} and V2X {self.v2x_hz} Hz")
        return replace(self, fps=self.fps // divisor, v2x_hz=self.v2x_hz // divisor)

    def describe(self) -> str:
        return (
            f"{self.cameras} cameras x {self.fps} fps x {self.boxes} boxes + V2X {self.v2x_hz} Hz "
            f"= {self.messages_per_s} msg/s"
        )


MIX = Mix()

Template = tuple[bytes, bytes]  # JSON before and after the stamp


@dataclass(frozen=True)
class Site:
    """Everything the publisher and the daemon's config need; picklable (sent to the publisher process)."""

    mix: Mix
    crs: str
    camera_ids: tuple[str, ...]
    intrinsics: tuple[CameraIntrinsics, ...]
    camera_lat_lon: tuple[tuple[float, float], ...]
    vehicle: VehicleProfile
    detection_templates: tuple[tuple[Template, ...], ...]  # per camera
    lap_templates: dict[
        str, tuple[Template, ...]
    ]  # loop "A" (past the cameras) / "B" (away): per V2X message
    pattern: str  # the loops driven, repeated

    @property
    def keys(self) -> tuple[str, ...]:
        """Bus keys by index: the cameras' detections, then the vehicle's V2X."""
        from daemon.keys import detections_key, v2x_key

        return (*(detections_key(RSU_ID, c) for c in self.camera_ids), v2x_key(STATION_ID))

    @property
    def loop_s(self) -> float:
        return len(self.lap_templates["A"]) / self.mix.v2x_hz


def _template(document: dict[str, Any]) -> Template:
    text = json.dumps(document, separators=(",", ":"))
    before, after = text.split(str(STAMP_SENTINEL))
    return before.encode(), after.encode()


def build_site(mix: Mix, pattern: str, passed_cameras: int | None = None) -> Site:
    """Cameras, detection frames and the vehicle's figure-eight around the source preset's site.

    The figure-eight: loop A (counter-clockwise) and loop B (clockwise) of ROUTE_RADIUS_M touch at the
    origin's south, where both head east, so the vehicle changes loops without a jump in position or heading.
    The first `passed_cameras` cameras (default all) stand around the top of loop A, the others
    OFF_ROUTE_M further north, where the vehicle never comes (their trackers still see every position).
    """
    import numpy as np

    from pipeline.frames import UtmFrame
    from sim.simulate import simulate

    sim = simulate(SOURCE_PRESET, 0)
    frame = UtmFrame(sim.origin.crs)
    east0, north0 = sim.origin.x, sim.origin.y
    camera_ids, intrinsics, positions, detection_templates = [], [], [], []
    for k in range(mix.cameras):
        camera_id = f"cam{k}"
        source = sim.cameras[k % len(sim.cameras)]
        angle = k * math.pi / 2.0
        off_route_m = 0.0 if passed_cameras is None or k < passed_cameras else OFF_ROUTE_M
        lat, lon = frame.to_wgs84(
            np.array([east0 + CAMERA_SPREAD_M * math.cos(angle)]),
            np.array([north0 + ROUTE_RADIUS_M + off_route_m + CAMERA_SPREAD_M * math.sin(angle)]),
        )
        boxes = [box.model_dump(mode="json") for f in sim.detections[source.camera_id] for box in f.boxes]
        templates = []
        for j in range(TEMPLATE_FRAMES):
            start = j * mix.boxes
            chosen = [boxes[(start + i) % len(boxes)] for i in range(mix.boxes)]
            templates.append(_template({"camera_id": camera_id, "stamp_ns": STAMP_SENTINEL, "boxes": chosen}))
        camera_ids.append(camera_id)
        intrinsics.append(source.intrinsics)
        positions.append((float(lat[0]), float(lon[0])))
        detection_templates.append(tuple(templates))

    steps = round(2.0 * math.pi * ROUTE_RADIUS_M * mix.v2x_hz / ROUTE_SPEED_MPS)
    speed_mps = 2.0 * math.pi * ROUTE_RADIUS_M * mix.v2x_hz / steps  # a whole number of messages per loop

    def loop(centre_north: float, start_angle: float, direction: float) -> tuple[Template, ...]:
        angles = start_angle + direction * 2.0 * math.pi * np.arange(steps) / steps
        east = east0 + ROUTE_RADIUS_M * np.cos(angles)
        north = centre_north + ROUTE_RADIUS_M * np.sin(angles)
        lat, lon = frame.to_wgs84(east, north)
        heading_deg = frame.heading_from_yaw(angles + direction * math.pi / 2.0, lat, lon)
        return tuple(
            _template(
                {
                    "station_id": STATION_ID,
                    "stamp_ns": STAMP_SENTINEL,
                    "lat": float(la),
                    "lon": float(lo),
                    "alt": sim.origin.z,
                    "heading_deg": float(h),
                    "speed": speed_mps,
                    "length": sim.vehicle.length,
                    "width": sim.vehicle.width,
                    "roll": 0.0,
                    "pitch": 0.0,
                    "accuracies": {"horizontal_m": 0.05, "vertical_m": 0.08, "heading_deg": 0.3},
                }
            )
            for la, lo, h in zip(lat, lon, heading_deg, strict=True)
        )

    laps = {
        "A": loop(north0, -math.pi / 2.0, 1.0),
        "B": loop(north0 - 2.0 * ROUTE_RADIUS_M, math.pi / 2.0, -1.0),
    }
    return Site(
        mix=mix,
        crs=sim.origin.crs,
        camera_ids=tuple(camera_ids),
        intrinsics=tuple(intrinsics),
        camera_lat_lon=tuple(positions),
        vehicle=sim.vehicle,
        detection_templates=tuple(detection_templates),
        lap_templates=laps,
        pattern=pattern,
    )


def mix_stream(site: Site, start_ns: int) -> Iterator[tuple[int, int, bytes]]:
    """(key index, stamp_ns, payload) of the mix in stamp order from start_ns, endless."""
    mix = site.mix
    if 1_000_000_000 % mix.fps or 1_000_000_000 % mix.v2x_hz:
        raise ValueError(f"{mix}: fps and V2X rate must divide one second in whole nanoseconds")
    frame_ns, v2x_ns = 1_000_000_000 // mix.fps, 1_000_000_000 // mix.v2x_hz
    events = sorted(
        [(k * CAMERA_PHASE_NS + i * frame_ns, k) for k in range(mix.cameras) for i in range(mix.fps)]
        + [(j * v2x_ns, mix.cameras) for j in range(mix.v2x_hz)]
    )
    detections = site.detection_templates
    loops = [site.lap_templates[name] for name in site.pattern]
    loop_len = len(loops[0])
    next_frame = [0] * mix.cameras
    next_v2x = 0
    second_ns = start_ns
    while True:
        for offset_ns, index in events:
            stamp_ns = second_ns + offset_ns
            if index < mix.cameras:
                templates = detections[index]
                before, after = templates[next_frame[index] % len(templates)]
                next_frame[index] += 1
            else:
                before, after = loops[(next_v2x // loop_len) % len(loops)][next_v2x % loop_len]
                next_v2x += 1
            yield index, stamp_ns, before + str(stamp_ns).encode() + after
        second_ns += 1_000_000_000


# ------------------------------------------------------------------------------------- publisher process


class _Stream:
    """mix_stream with one message of look-ahead, so a command can stop before a message it did not send."""

    def __init__(self, site: Site, start_ns: int) -> None:
        self._messages = mix_stream(site, start_ns)
        self.head = next(self._messages)

    def advance(self) -> None:
        self.head = next(self._messages)


def _publish(
    stream: _Stream, puts: Sequence[Callable[[bytes], Any]], command: dict[str, Any]
) -> dict[str, Any]:
    """Publish per `command` (see PublisherProcess); -> counts, seconds, how far behind its stamps."""
    kind = command["kind"]
    counts = [0] * len(puts)
    published = 0
    max_lag_s = 0.0
    started = time.perf_counter()
    if kind == "paced":
        rate, duration_s = command["rate"], command["duration_s"]
        while True:
            if published % 32 == 0:  # pace in small batches: perf_counter per message would cost ~5 %
                elapsed = time.perf_counter() - started
                if elapsed >= duration_s:
                    break
                if rate is not None and published / rate > elapsed:
                    time.sleep(published / rate - elapsed)
            index, _, payload = stream.head
            puts[index](payload)
            counts[index] += 1
            published += 1
            stream.advance()
    else:
        # "realtime": a stamp is due at that wall time; "scaled": when the daemon's ScaledClock reaches it.
        end_ns = command["end_ns"]
        scaled = kind == "scaled"
        clock_start_ns, rate, t0_mono_ns = command.get("clock_start_ns", 0), command.get("rate", 1.0), 0
        if scaled:
            t0_mono_ns = command["t0_mono_ns"]
        while True:
            index, stamp_ns, payload = stream.head
            if stamp_ns >= end_ns:
                break
            if scaled:
                wait_s = (t0_mono_ns + (stamp_ns - clock_start_ns) / rate - time.monotonic_ns()) / 1e9
            else:
                wait_s = (stamp_ns - time.time_ns()) / 1e9
            if wait_s > 0.0:
                time.sleep(wait_s)
            else:
                max_lag_s = max(max_lag_s, -wait_s)
            puts[index](payload)
            counts[index] += 1
            published += 1
            stream.advance()
    seconds = time.perf_counter() - started
    return {
        "published": published,
        "by_key": counts,
        "seconds": seconds,
        "rate_msgs_s": published / seconds if seconds > 0 else 0.0,
        "max_lag_s": max_lag_s,
        "next_stamp_ns": stream.head[1],
    }


def _is_matched(publisher: zenoh.Publisher) -> bool:
    """Whether a subscriber matches (zenoh 1.x returns a MatchingStatus; its stubs say bool)."""
    status: Any = publisher.matching_status
    return bool(getattr(status, "matching", status))


def _publisher_main(conn: Connection, site: Site, endpoint: str) -> None:
    """The publisher process: one session, one BLOCK publisher per key; runs the commands it is sent."""
    import zenoh

    from daemon.bus import client_config

    session = zenoh.open(client_config([endpoint]))
    publishers: list[zenoh.Publisher] = []
    try:
        publishers = [
            session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)
            for key in site.keys
        ]
        # A put before the daemon's subscriptions are known here goes nowhere: wait until every key matches.
        deadline = time.monotonic() + MATCH_TIMEOUT_S
        while not all(_is_matched(p) for p in publishers):
            if time.monotonic() > deadline:
                conn.send({"error": f"no subscriber matched within {MATCH_TIMEOUT_S} s on {endpoint}"})
                return
            time.sleep(0.01)
        conn.send({"ready": True})
        puts = [p.put for p in publishers]
        stream: _Stream | None = None
        while True:
            command = conn.recv()
            if command["kind"] == "stop":
                return
            if stream is None:
                stream = _Stream(site, command["start_ns"])
            conn.send(_publish(stream, puts, command))
    finally:
        for publisher in publishers:
            publisher.undeclare()  # type: ignore[no-untyped-call]
        session.close()  # type: ignore[no-untyped-call]


class PublisherProcess:
    """The RSU's cameras and the vehicle, in a spawned process of their own. Commands (dicts, one at a time):
    {"kind": "realtime", "start_ns", "end_ns"}: each message at its stamp's wall time;
    {"kind": "paced", "start_ns", "rate" (msg/s or None: as fast as possible), "duration_s"};
    {"kind": "scaled", "start_ns", "end_ns", "clock_start_ns", "rate", "t0_mono_ns"}: each message when a
    ScaledClock(clock_start_ns, rate) created at monotonic t0_mono_ns reaches its stamp.
    start_ns, the first stamp, counts only in the first command: the stream continues across commands."""

    def __init__(self, site: Site, endpoint: str) -> None:
        context = multiprocessing.get_context("spawn")
        self._conn, child = context.Pipe()
        self._process = context.Process(
            target=_publisher_main, args=(child, site, endpoint), name="bench-publisher", daemon=True
        )

    def start(self, timeout_s: float = 60.0) -> None:
        self._process.start()
        if not self._conn.poll(timeout_s):
            raise RuntimeError(f"publisher process not ready within {timeout_s} s")
        answer = self._conn.recv()
        if "error" in answer:
            raise RuntimeError(f"publisher process: {answer['error']}")

    @property
    def pid(self) -> int | None:
        return self._process.pid

    def send(self, command: dict[str, Any]) -> None:
        self._conn.send(command)

    def poll(self, timeout_s: float) -> bool:
        """True when the running command's report is ready."""
        if not self._process.is_alive() and not self._conn.poll():
            raise RuntimeError(f"publisher process died (exit code {self._process.exitcode})")
        return self._conn.poll(timeout_s)

    def report(self) -> dict[str, Any]:
        answer: dict[str, Any] = self._conn.recv()
        return answer

    def close(self) -> None:
        if self._process.is_alive():
            with contextlib.suppress(OSError):
                self._conn.send({"kind": "stop"})
            self._process.join(5.0)
        if self._process.is_alive():
            self._process.terminate()
            self._process.join(2.0)


# ------------------------------------------------------------------------------------------- the daemon


def site_config(
    site: Site,
    state_dir: Path,
    port: int,
    trigger: TriggerConfig | None = None,
    storage: StorageConfig | None = None,
    jobs: JobsConfig | None = None,
) -> DaemonConfig:
    """The config an installer would write for the bench site; by default no job ever starts (throughput)."""
    from schemas.config import (
        CalibrationVehicle,
        CameraConfig,
        DaemonConfig,
        GeoPoint,
        JobsConfig,
        StorageConfig,
        TriggerConfig,
        ZenohConfig,
    )

    cameras = [
        CameraConfig(
            camera_id=camera_id,
            intrinsics=intrinsics,
            position=GeoPoint(lat=lat, lon=lon),
            coverage_radius_m=COVERAGE_RADIUS_M,
        )
        for camera_id, intrinsics, (lat, lon) in zip(
            site.camera_ids, site.intrinsics, site.camera_lat_lon, strict=True
        )
    ]
    return DaemonConfig(
        rsu_id=RSU_ID,
        crs=site.crs,
        zenoh=ZenohConfig(listen=[f"tcp/127.0.0.1:{port}"]),
        cameras=cameras,
        vehicles=[CalibrationVehicle(station_id=STATION_ID, profile=site.vehicle)],
        # Throughput runs: traversals are counted, but a job would need 100 of them and a day's quiet.
        trigger=trigger or TriggerConfig(min_traversals=100, quiet_period_s=86_400.0),
        storage=storage or StorageConfig(state_dir=state_dir),
        jobs=jobs or JobsConfig(max_parallel=1, track_workers=1),
    )


@dataclass(frozen=True, slots=True)
class Sample:
    """The daemon's health counters at one moment, with its process's CPU time and RSS."""

    t_s: float  # time.monotonic()
    received: int
    accepted: int
    dropped: int
    rejected: int
    inbox_depth: int
    recordings_bytes: int
    recordings_files: int
    cpu_s: float
    rss_bytes: int
    counters: dict[str, int] = field(repr=False)


def to_sample(health: Health, pid: int | None) -> Sample:
    counters = health.counters
    usage = process_usage(pid)
    return Sample(
        t_s=time.monotonic(),
        received=counters.get("detections.received", 0) + counters.get("v2x.received", 0),
        accepted=counters.get("detections.accepted", 0) + counters.get("v2x.accepted", 0),
        dropped=counters.get("inbox.dropped", 0),
        rejected=sum(v for k, v in counters.items() if ".rejected" in k),
        inbox_depth=health.inbox_depth,
        recordings_bytes=health.disk.recordings_bytes if health.disk is not None else 0,
        recordings_files=health.disk.recordings_files if health.disk is not None else 0,
        cpu_s=usage.cpu_s,
        rss_bytes=usage.rss_bytes,
        counters=dict(counters),
    )


def query_health(session: zenoh.Session, timeout_s: float = HEALTH_TIMEOUT_S) -> Health | None:
    """The daemon's health over the bus, as any monitoring client reads it."""
    from daemon.bus import query
    from daemon.keys import health_key
    from schemas.common import decode_json
    from schemas.results import Health

    replies = query(session, health_key(RSU_ID), timeout_s=timeout_s)
    return decode_json(Health, replies[0][1]) if replies else None


class Monitor:
    """Samples a daemon over the bus (health) and from /proc (CPU, RSS of its process)."""

    def __init__(self, session: zenoh.Session, pid: int | None) -> None:
        self.session = session
        self.pid = pid

    def sample(self) -> Sample:
        health = query_health(self.session)
        if health is None:
            raise RuntimeError("the daemon did not answer its health query")
        return to_sample(health, self.pid)

    def wait_drained(self, accounted: int, timeout_s: float, interval_s: float = 0.05) -> tuple[Sample, bool]:
        """Poll until `accounted` messages were accepted, rejected or dropped and the inbox is empty."""
        deadline = time.monotonic() + timeout_s
        while True:
            sample = self.sample()
            done = sample.inbox_depth == 0 and sample.accepted + sample.rejected + sample.dropped >= accounted
            if done or time.monotonic() > deadline:
                return sample, done
            time.sleep(interval_s)


@contextlib.contextmanager
def client_session(endpoint: str) -> Iterator[zenoh.Session]:
    import zenoh

    from daemon.bus import client_config

    session = zenoh.open(client_config([endpoint]))
    try:
        yield session
    finally:
        session.close()  # type: ignore[no-untyped-call]


class DaemonProcess:
    """`python -m daemon.cli daemon --config rsu.yaml`: the product's own start-up, in its own process."""

    def __init__(self, config: DaemonConfig, directory: Path) -> None:
        self.config = config
        self.config_path = directory / "rsu.yaml"
        self.log_path = directory / "daemon.log"
        self.config_path.write_text(json.dumps(config.model_dump(mode="json"), indent=1))  # JSON is YAML
        self._process: subprocess.Popen[bytes] | None = None

    @property
    def pid(self) -> int:
        assert self._process is not None
        return self._process.pid

    def start(self, session: zenoh.Session, timeout_s: float = 60.0) -> None:
        with self.log_path.open("wb") as log_file:
            self._process = subprocess.Popen(
                [sys.executable, "-m", "daemon.cli", "daemon", "--config", str(self.config_path)],
                cwd=REPO_ROOT,
                stdout=log_file,
                stderr=subprocess.STDOUT,
            )
        deadline = time.monotonic() + timeout_s
        while query_health(session, timeout_s=1.0) is None:
            if self._process.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(
                    f"the daemon did not come up; its log:\n{self.log_path.read_text()[-3000:]}"
                )
            time.sleep(0.1)

    def stop(self) -> tuple[int | None, float]:
        """SIGTERM; -> exit code (None if it had to be killed) and seconds until it exited."""
        if self._process is None:
            return None, 0.0
        started = time.monotonic()
        self._process.send_signal(signal.SIGTERM)
        try:
            code: int | None = self._process.wait(timeout=10.0)
        except subprocess.TimeoutExpired:
            self._process.kill()
            self._process.wait()
            code = None
        return code, time.monotonic() - started

    def problems(self) -> list[str]:
        """WARNING/ERROR lines of the daemon's log."""
        lines = self.log_path.read_text(errors="replace").splitlines() if self.log_path.exists() else []
        return [line for line in lines if " WARNING " in line or " ERROR " in line or "Traceback" in line]


# The received messages' channels; the Foxglove views beside them (storage.foxglove_views) are not counted.
INPUT_SCHEMAS = frozenset({"rsucal.DetectionFrame", "rsucal.V2xPosition"})


def mcap_summary(directory: Path) -> tuple[int, int, int]:
    """(files, bytes, messages received) of the MCAP files in `directory`, from each file's statistics:
    messages on the raw DetectionFrame / V2xPosition channels only."""
    from mcap.reader import make_reader

    files = sorted(directory.glob("*.mcap"))
    messages = 0
    for path in files:
        with path.open("rb") as stream:
            summary = make_reader(stream).get_summary()
        if summary is not None and summary.statistics is not None:
            counts = summary.statistics.channel_message_counts
            for channel_id, channel in summary.channels.items():
                schema = summary.schemas.get(channel.schema_id)
                if schema is not None and schema.name in INPUT_SCHEMAS:
                    messages += counts.get(channel_id, 0)
    return len(files), sum(p.stat().st_size for p in files), messages


@dataclass
class LogTally:
    """Records per level, and the first few WARNING-and-above messages."""

    levels: Counter[str] = field(default_factory=Counter)
    problems: list[str] = field(default_factory=list)


@contextlib.contextmanager
def daemon_log(path: Path) -> Iterator[LogTally]:
    """Send this process's daemon logging (INFO and up, as `rsucal daemon` logs) to `path`; tally it."""
    tally = LogTally()

    class Counting(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            tally.levels[record.levelname] += 1
            if record.levelno >= logging.WARNING and len(tally.problems) < 10:
                tally.problems.append(f"{record.levelname} {record.name}: {record.getMessage()}"[:300])

    root = logging.getLogger()
    handlers = [logging.FileHandler(path), Counting()]
    handlers[0].setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    previous = root.level
    root.setLevel(logging.INFO)
    for handler in handlers:
        root.addHandler(handler)
    try:
        yield tally
    finally:
        for handler in handlers:
            root.removeHandler(handler)
            handler.close()
        root.setLevel(previous)


def _mb(n_bytes: float) -> float:
    return n_bytes / 1e6


def _cpu_pct(a: Sample, b: Sample) -> float:
    return 100.0 * (b.cpu_s - a.cpu_s) / max(1e-9, b.t_s - a.t_s)


# -------------------------------------------------------------------------------------------- sustained


@dataclass
class CliRig:
    """`rsucal daemon` in its own process, the publisher process and a monitoring client, on one port."""

    directory: Path
    daemon: DaemonProcess
    publisher: PublisherProcess
    monitor: Monitor
    exit_code: int | None = None  # None: never stopped cleanly (killed)
    stop_s: float = float("nan")
    mcap: tuple[int, int, int] = (0, 0, 0)  # files, bytes, messages, read after the daemon stopped
    problems: list[str] = field(default_factory=list)


@contextlib.contextmanager
def cli_rig(site: Site, foxglove_views: bool = True) -> Iterator[CliRig]:
    """Start the daemon and the publisher; on exit stop both (SIGTERM timed) and read the MCAP summary.
    `foxglove_views`: storage.foxglove_views (the recording's LocationFix / ImageAnnotations beside the raw
    channels; on by default, as in the field)."""
    from daemon.bus import free_loopback_port
    from schemas.config import StorageConfig

    with tempfile.TemporaryDirectory(prefix="rsucal-bench-daemon-") as tmp:
        directory = Path(tmp)
        port = free_loopback_port()
        endpoint = f"tcp/127.0.0.1:{port}"
        storage = StorageConfig(state_dir=directory / "state", foxglove_views=foxglove_views)
        config = site_config(site, directory / "state", port, storage=storage)
        daemon = DaemonProcess(config, directory)
        publisher = PublisherProcess(site, endpoint)
        with client_session(endpoint) as client:
            rig: CliRig | None = None
            try:
                daemon.start(client)
                rig = CliRig(directory, daemon, publisher, Monitor(client, daemon.pid))
                publisher.start()
                yield rig
            finally:
                publisher.close()
                code, stop_s = daemon.stop()
                if rig is not None:
                    rig.exit_code, rig.stop_s = code, stop_s
        if rig is not None:
            rig.mcap = mcap_summary(directory / "state" / "recordings")
            rig.problems = daemon.problems()


def run_sustained(seconds: float) -> dict[str, Any]:
    """The CLI daemon fed the mix in real time by the publisher process; every message must be accepted."""
    with cli_rig(build_site(MIX, THROUGHPUT_PATTERN)) as rig:
        monitor, publisher = rig.monitor, rig.publisher
        before = monitor.sample()
        start_ns = time.time_ns() + 500_000_000
        publisher.send({"kind": "realtime", "start_ns": start_ns, "end_ns": start_ns + int(seconds * 1e9)})
        samples = [before]
        while not publisher.poll(1.0):
            samples.append(monitor.sample())
        report = publisher.report()
        after, drained = monitor.wait_drained(before.accepted + report["published"], 10.0)
        samples.append(after)
    files, mcap_bytes, mcap_messages = rig.mcap
    code, stop_s, problems = rig.exit_code, rig.stop_s, rig.problems
    published = report["published"]
    accepted = after.accepted - before.accepted
    duration_s = report["seconds"]
    # The inbox depth at 1 s intervals; a daemon keeping up shows 0 (a few at most) throughout.
    depths = [s.inbox_depth for s in samples]
    result = {
        "mix": MIX.describe(),
        "seconds": duration_s,
        "published": published,
        "published_detections": sum(report["by_key"][:-1]),
        "published_v2x": report["by_key"][-1],
        "received": after.received - before.received,
        "accepted": accepted,
        "accepted_detections": after.counters.get("detections.accepted", 0)
        - before.counters.get("detections.accepted", 0),
        "accepted_v2x": after.counters.get("v2x.accepted", 0) - before.counters.get("v2x.accepted", 0),
        "dropped": after.dropped - before.dropped,
        "rejected": after.rejected - before.rejected,
        "lost": published - accepted,
        "publisher_max_lag_s": report["max_lag_s"],
        "inbox_depth_max": max(depths),
        "inbox_depth_mean": sum(depths) / len(depths),
        "inbox_depth_series": depths,
        "cpu_pct": _cpu_pct(before, samples[-2] if len(samples) > 2 else after),
        "rss_mb_start": _mb(before.rss_bytes),
        "rss_mb_end": _mb(after.rss_bytes),
        "mcap_files": files,
        "mcap_bytes": mcap_bytes,
        "mcap_bytes_per_s": mcap_bytes / duration_s,
        "mcap_messages": mcap_messages,
        "drained": drained,
        "exit_code": code,
        "stop_s": stop_s,
        "log_problems": problems[:10],
    }
    result["passed"] = (
        result["lost"] == 0
        and result["dropped"] == 0
        and result["rejected"] == 0
        and drained
        and mcap_messages == accepted
    )
    return result


def print_sustained(r: dict[str, Any]) -> None:
    print(f"\n== sustained: `rsucal daemon` fed {r['mix']} in real time for {r['seconds']:.0f} s")
    rows = [
        (
            "published (detections + V2X)",
            f"{r['published']} ({r['published_detections']} + {r['published_v2x']})",
        ),
        ("received by the decoder", f"{r['received']}"),
        (
            "accepted (detections + V2X)",
            f"{r['accepted']} ({r['accepted_detections']} + {r['accepted_v2x']})",
        ),
        ("dropped (inbox full) / rejected", f"{r['dropped']} / {r['rejected']}"),
        ("lost (published - accepted)", f"{r['lost']}"),
        ("inbox depth, 1 s samples: max / mean", f"{r['inbox_depth_max']} / {r['inbox_depth_mean']:.2f}"),
        ("CPU of the daemon process", f"{r['cpu_pct']:.1f} % of one core"),
        ("RSS of the daemon process", f"{r['rss_mb_start']:.0f} MB -> {r['rss_mb_end']:.0f} MB"),
        (
            "MCAP",
            f"{r['mcap_bytes'] / 1e6:.1f} MB in {r['mcap_files']} file(s), "
            f"{r['mcap_bytes_per_s'] / 1e3:.0f} kB/s, {r['mcap_messages']} messages",
        ),
        ("publisher behind its stamps, max", f"{r['publisher_max_lag_s'] * 1e3:.1f} ms"),
        ("SIGTERM -> exit", f"{r['stop_s']:.2f} s, exit code {r['exit_code']}"),
    ]
    for name, value in rows:
        print(f"  {name:<40}{value}")
    series = r["inbox_depth_series"]
    print(f"  inbox depth every 10 s: {' '.join(str(d) for d in series[::10])}")
    for line in r["log_problems"]:
        print(f"  daemon log: {line}")
    print(
        f"{'PASS' if r['passed'] else 'FAIL'}  sustained: every message accepted and in the MCAP "
        f"(lost {r['lost']}, dropped {r['dropped']}, rejected {r['rejected']}, "
        f"MCAP {r['mcap_messages']} of {r['accepted']})"
    )


# ---------------------------------------------------------------------------------------------- ceiling


def run_ceiling(
    rates: Sequence[float], step_s: float, py_spy_rate: float | None = None, foxglove_views: bool = True
) -> dict[str, Any]:
    """Steps of increasing rate, the mix time-compressed; then one unpaced step."""
    steps: list[dict[str, Any]] = []
    py_spy: dict[str, Any] | None = None
    with cli_rig(build_site(MIX, THROUGHPUT_PATTERN), foxglove_views) as rig:
        failures = 0
        plan: list[float | None] = [*rates, None]
        for rate in plan:
            if rate is not None and failures >= FAILED_STEPS_BEFORE_SKIP:
                steps.append({"rate": rate, "skipped": True, "passed": False})
                continue
            spy = None
            if rate is not None and py_spy_rate is not None and rate == py_spy_rate:
                spy = PySpy.start(rig.daemon.pid, step_s, rig.directory / f"py-spy-{rate:.0f}.txt")
            step = _ceiling_step(rig.monitor, rig.publisher, rate, step_s)
            if spy is not None:
                py_spy = spy.finish()
            steps.append(step)
            if rate is not None:
                failures = 0 if step["passed"] else failures + 1
    files, mcap_bytes, mcap_messages = rig.mcap
    code, stop_s, problems = rig.exit_code, rig.stop_s, rig.problems
    passing = [s["rate"] for s in steps if s.get("passed")]
    ceiling = max(passing, default=0.0)
    accepted_total = sum(s.get("accepted", 0) for s in steps)
    return {
        "mix": MIX.describe(),
        "foxglove_views": foxglove_views,
        "step_s": step_s,
        "steps": steps,
        "ceiling_msgs_s": ceiling,
        "mcap_files": files,
        "mcap_bytes": mcap_bytes,
        "mcap_messages": mcap_messages,
        "accepted_total": accepted_total,
        "exit_code": code,
        "stop_s": stop_s,
        "log_problems": problems[:10],
        "py_spy": py_spy,
        "passed": ceiling >= CEILING_TARGET_MSGS_S,
    }


def _ceiling_step(
    monitor: Monitor, publisher: PublisherProcess, rate: float | None, step_s: float
) -> dict[str, Any]:
    publisher_pid = publisher.pid
    publisher_cpu_s = process_usage(publisher_pid).cpu_s if publisher_pid is not None else 0.0
    before = monitor.sample()
    publisher.send({"kind": "paced", "start_ns": time.time_ns(), "rate": rate, "duration_s": step_s})
    max_depth = before.inbox_depth
    while not publisher.poll(0.5):
        max_depth = max(max_depth, monitor.sample().inbox_depth)
    report = publisher.report()
    if publisher_pid is not None:
        publisher_cpu_s = process_usage(publisher_pid).cpu_s - publisher_cpu_s
    at_end = monitor.sample()
    max_depth = max(max_depth, at_end.inbox_depth)
    accounted = before.accepted + before.rejected + before.dropped + report["published"]
    timeout_s = DRAIN_TIMEOUT_S if rate is not None else 3.0 * DRAIN_TIMEOUT_S
    after, drained = monitor.wait_drained(accounted, timeout_s)
    drain_s = after.t_s - at_end.t_s if drained else float("inf")
    published = report["published"]
    accepted = after.accepted - before.accepted
    seconds = report["seconds"]
    step = {
        "rate": rate,
        "published": published,
        "published_rate": report["rate_msgs_s"],
        "accepted": accepted,
        "dropped": after.dropped - before.dropped,
        "rejected": after.rejected - before.rejected,
        "lost": published - accepted,
        "accepted_rate_in_step": (at_end.accepted - before.accepted) / max(1e-9, at_end.t_s - before.t_s),
        "inbox_depth_max": max_depth,
        "inbox_depth_at_end": at_end.inbox_depth,
        "drain_s": drain_s,
        "processed_rate": published / (seconds + drain_s),
        "cpu_pct": _cpu_pct(before, at_end),
        "publisher_cpu_pct": 100.0 * publisher_cpu_s / max(1e-9, seconds),
        "rss_mb": _mb(after.rss_bytes),
    }
    step["passed"] = (
        rate is not None
        and drained
        and step["lost"] == 0
        and step["dropped"] == 0
        and step["rejected"] == 0
        and step["published_rate"] >= PUBLISHED_SHARE * rate
        and step["processed_rate"] >= PROCESSED_SHARE * rate
    )
    return step


def print_ceiling(r: dict[str, Any]) -> None:
    views = "on" if r.get("foxglove_views", True) else "off"
    print(
        f"\n== ceiling: `rsucal daemon`, {r['mix']} time-compressed, {r['step_s']:.0f} s per rate; "
        f"Foxglove views {views} (storage.foxglove_views)"
    )
    header = (
        f"{'target/s':>9}{'published/s':>12}{'accepted':>10}{'lost':>7}{'dropped':>8}{'rejected':>9}"
        f"{'in-step acc/s':>14}{'inbox max':>10}{'at end':>8}{'drain s':>8}{'processed/s':>12}{'CPU %':>7}"
        f"{'pub %':>6}"
        f"{'RSS MB':>7}  result"
    )
    print(header)
    print("-" * len(header))
    for s in r["steps"]:
        target = "max" if s["rate"] is None else f"{s['rate']:.0f}"
        if s.get("skipped"):
            print(f"{target:>9}  (skipped after {FAILED_STEPS_BEFORE_SKIP} failed rates)")
            continue
        verdict = "info" if s["rate"] is None else ("PASS" if s["passed"] else "FAIL")
        print(
            f"{target:>9}{s['published_rate']:>12.0f}{s['accepted']:>10}{s['lost']:>7}{s['dropped']:>8}"
            f"{s['rejected']:>9}{s['accepted_rate_in_step']:>14.0f}{s['inbox_depth_max']:>10}"
            f"{s['inbox_depth_at_end']:>8}{s['drain_s']:>8.2f}{s['processed_rate']:>12.0f}{s['cpu_pct']:>7.0f}"
            f"{s['publisher_cpu_pct']:>6.0f}"
            f"{s['rss_mb']:>7.0f}  {verdict}"
        )
    print(
        "  CPU % = the daemon process (100 = one core), pub % = the publisher process; in-step acc/s = "
        "accepted per second while publishing; processed/s = published / (step + drain)"
    )
    print(
        f"  a rate passes with lost = dropped = rejected = 0, published >= {PUBLISHED_SHARE:.0%} of it and "
        f"processed = published / (step + drain) >= {PROCESSED_SHARE:.0%} of it"
    )
    print(
        f"  MCAP: {r['mcap_messages']} messages in {r['mcap_files']} file(s), {r['mcap_bytes'] / 1e6:.0f} MB "
        f"(accepted {r['accepted_total']}); SIGTERM -> exit {r['stop_s']:.2f} s, code {r['exit_code']}"
    )
    for line in r["log_problems"]:
        print(f"  daemon log: {line}")
    if r.get("py_spy"):
        print_py_spy(r["py_spy"])
    print(
        f"{'PASS' if r['passed'] else 'FAIL'}  ceiling {r['ceiling_msgs_s']:.0f} msg/s with zero loss "
        f"(target >= {CEILING_TARGET_MSGS_S:.0f})"
    )


# -------------------------------------------------------------------------------------------------- rss


def run_rss(hours: int, rate: float, divisor: int, trace: bool = False) -> dict[str, Any]:
    """A simulated day into an in-process Daemon on a ScaledClock; RSS every simulated hour. With `trace`,
    tracemalloc runs too (slower): Python-allocated bytes per hour and the lines that grew after hour 1."""
    import tracemalloc

    from daemon.bus import free_loopback_port, query
    from daemon.clock import ScaledClock
    from daemon.keys import status_key
    from daemon.main import Daemon, DaemonEvent
    from schemas.config import JobsConfig, StorageConfig, TriggerConfig

    mix = MIX.divided(divisor)
    site = build_site(mix, RSS_PATTERN, RSS_PASSED_CAMERAS)
    events: Counter[str] = Counter()
    job_texts: list[str] = []

    def on_event(event: DaemonEvent) -> None:
        events[event.kind] += 1
        if event.kind not in ("entered", "left", "discarded") and len(job_texts) < 12:
            job_texts.append(f"{event.camera_id}: {event.text}"[:200])

    rows: list[dict[str, Any]] = []
    queries = 0
    first_snapshot: tracemalloc.Snapshot | None = None
    growth_lines: list[str] = []
    with tempfile.TemporaryDirectory(prefix="rsucal-bench-daemon-") as tmp:
        directory = Path(tmp)
        port = free_loopback_port()
        endpoint = f"tcp/127.0.0.1:{port}"
        config = site_config(
            site,
            directory / "state",
            port,
            trigger=TriggerConfig(min_traversals=3, quiet_period_s=60.0, max_window_s=3600.0),
            storage=StorageConfig(
                state_dir=directory / "state",
                rotate_s=1800.0,
                rotate_bytes=4 * MIB,
                # By age; long enough that a job's files outlive its run even at RSS rate (a 10 s job is
                # 80 simulated minutes at 480x and the tracker protects its window for max_window_s only).
                retention_s=4 * 3600.0,
                retention_bytes=GIB,
            ),
            jobs=JobsConfig(max_parallel=1, track_workers=1),
        )
        clock = ScaledClock(RSS_START_NS, rate)
        stop = threading.Event()
        publisher = PublisherProcess(site, endpoint)
        with daemon_log(directory / "daemon.log") as log_tally, contextlib.ExitStack() as stack:
            if trace:
                tracemalloc.start(1)
            daemon = Daemon(config, clock=clock, on_event=on_event)
            daemon.start()
            started = time.monotonic()
            try:
                # Opened once the daemon listens: a session that found nobody retries only after a while.
                client = stack.enter_context(client_session(endpoint))
                publisher.start()
                # The publisher maps stamps to wall time as this clock does (CLOCK_MONOTONIC is system-wide).
                t0_mono_ns = time.monotonic_ns() - int((clock.now_ns() - RSS_START_NS) / rate)
                # The day starts with the first message (the clock ran while the publisher process started).
                first_ns = clock.now_ns() + 1_000_000_000
                end_ns = first_ns + int(hours * 3600e9)
                publisher.send(
                    {
                        "kind": "scaled",
                        "start_ns": first_ns,
                        "end_ns": end_ns,
                        "clock_start_ns": RSS_START_NS,
                        "rate": rate,
                        "t0_mono_ns": t0_mono_ns,
                    }
                )
                steps = int(hours * 3600 / RSS_QUERY_EVERY_S)
                per_hour = int(3600 / RSS_QUERY_EVERY_S)
                for step in range(1, steps + 1):
                    if not clock.sleep_until(first_ns + int(step * RSS_QUERY_EVERY_S * 1e9), stop):
                        break
                    health = query_health(client)
                    for camera_id in site.camera_ids:
                        query(client, status_key(RSU_ID, camera_id), timeout_s=HEALTH_TIMEOUT_S)
                    queries += 1 + len(site.camera_ids)
                    if step % per_hour == 0 and health is not None:
                        sample = to_sample(health, None)
                        status = daemon.status(site.camera_ids[0])
                        rows.append(
                            {
                                "hour": step // per_hour,
                                "wall_s": time.monotonic() - started,
                                "rss_mb": _mb(sample.rss_bytes),
                                # Python objects alive (pymalloc blocks): grows with a leak, not with
                                # fragmentation or a high-water mark the allocator keeps.
                                "blocks_k": sys.getallocatedblocks() / 1e3,
                                "traced_mb": _mb(tracemalloc.get_traced_memory()[0]) if trace else None,
                                "accepted": sample.accepted,
                                "dropped": sample.dropped,
                                "rejected": sample.rejected,
                                "inbox_depth": sample.inbox_depth,
                                "files": sample.recordings_files,
                                "recordings_mb": _mb(sample.recordings_bytes),
                                "written_files": daemon.recorder.files_written,
                                "pruned": sample.counters.get("recordings.pruned", 0),
                                "traversals_counted": events["left"],
                                "window_traversals": status.traversals,
                                "jobs": events["job_started"],
                                "jobs_done": sum(
                                    events[k] for k in ("published", "verified", "refused", "failed")
                                ),
                            }
                        )
                        if trace and rows[-1]["hour"] == 1:
                            first_snapshot = tracemalloc.take_snapshot()
                        print(
                            f"  [rss] hour {rows[-1]['hour']:>2} ({rows[-1]['wall_s']:5.0f} s): "
                            f"RSS {rows[-1]['rss_mb']:.1f} MB, {sample.accepted} accepted",
                            file=sys.stderr,
                            flush=True,
                        )
                while not publisher.poll(1.0):
                    pass
                report = publisher.report()
                if trace and first_snapshot is not None:
                    growth_lines = [
                        f"{diff.size_diff / 1e6:+8.3f} MB {diff.count_diff:+8d} blocks  {diff.traceback}"
                        for diff in tracemalloc.take_snapshot().compare_to(first_snapshot, "lineno")[:12]
                    ]
            finally:
                stop.set()
                publisher.close()
                daemon.stop()
                if trace:
                    tracemalloc.stop()
            wall_s = time.monotonic() - started
    first, last = (rows[0], rows[-1]) if rows else ({"rss_mb": math.nan}, {"rss_mb": math.nan})
    growth = (last["rss_mb"] - first["rss_mb"]) / first["rss_mb"]
    return {
        "mix": mix.describe(),
        "hours": hours,
        "rate": rate,
        "wall_s": wall_s,
        "published": report["published"],
        "publisher_max_lag_s": report["max_lag_s"],
        "rows": rows,
        "queries": queries,
        "events": dict(events),
        "job_texts": job_texts,
        "tracemalloc_growth": growth_lines,
        "log_levels": dict(log_tally.levels),
        "log_problems": log_tally.problems,
        "growth": growth,
        "passed": bool(rows) and abs(growth) <= RSS_GROWTH_LIMIT and last.get("dropped", 1) == 0,
    }


def print_rss(r: dict[str, Any]) -> None:
    print(
        f"\n== rss: a Daemon in this process, {r['hours']} h simulated at {r['rate']:g}x in "
        f"{r['wall_s']:.0f} s wall, fed {r['mix']} through Zenoh from the publisher process"
    )
    print(
        "  (detection and V2X rates divided for the replay, message sizes kept; rotation 30 min / 4 MiB, "
        "retention 4 h;\n  health + 4 statuses queried over Zenoh every simulated 5 min; the vehicle passes "
        "cam0 4 times every 8 h, the other cameras are off its route)"
    )
    header = (
        f"{'hour':>5}{'wall s':>8}{'RSS MB':>8}{'blocks k':>9}{'accepted':>10}{'dropped':>8}{'rejected':>9}"
        f"{'inbox':>7}{'files':>6}{'rec MB':>8}{'written':>8}{'pruned':>7}{'left ev':>8}{'in window':>10}"
        f"{'jobs':>5}{'done':>5}"
    )
    print(header)
    print("-" * len(header))
    for row in r["rows"]:
        print(
            f"{row['hour']:>5}{row['wall_s']:>8.0f}{row['rss_mb']:>8.1f}{row['blocks_k']:>9.0f}{row['accepted']:>10}{row['dropped']:>8}"
            f"{row['rejected']:>9}{row['inbox_depth']:>7}{row['files']:>6}{row['recordings_mb']:>8.1f}"
            f"{row['written_files']:>8}{row['pruned']:>7}{row['traversals_counted']:>8}"
            f"{row['window_traversals']:>10}{row['jobs']:>5}{row['jobs_done']:>5}"
        )
    print(
        f"  published {r['published']} messages (publisher at most {r['publisher_max_lag_s']:.2f} s behind "
        f"the scaled clock); {r['queries']} queries; events {r['events']}; log records {r['log_levels']}"
    )
    for line in r["job_texts"]:
        print(f"  job: {line}")
    if r["tracemalloc_growth"]:
        traced = [f"{row['traced_mb']:.1f}" for row in r["rows"]]
        print(f"  tracemalloc: Python-allocated MB per hour: {' '.join(traced)}")
        print("  tracemalloc: largest growth from hour 1 to the end, by line:")
        for line in r["tracemalloc_growth"]:
            print(f"    {line}")
    for line in r["log_problems"]:
        print(f"  daemon log: {line}")
    print(
        f"{'PASS' if r['passed'] else 'FAIL'}  RSS after hour {r['rows'][-1]['hour'] if r['rows'] else '-'} "
        f"within {RSS_GROWTH_LIMIT:.0%} of hour 1 ({r['growth']:+.1%}), nothing dropped"
    )


# ---------------------------------------------------------------------------------------------- latency


def run_latency(rate: float, quiet_period_s: float, seed: int) -> dict[str, Any]:
    """The `long` preset into a Daemon; per job: quiet-period end -> job start -> result on the bus."""
    import zenoh

    from daemon.bus import free_loopback_port
    from daemon.clock import ScaledClock
    from daemon.demo import demo_config, publish_messages, simulation_messages
    from daemon.keys import calibration_key
    from daemon.main import Daemon, DaemonEvent
    from schemas.config import JobsConfig
    from sim.simulate import simulate

    # The ideal world: this part times the daemon from a quiet period's end to a calibration on the bus, so
    # the scene must be one the method calibrates (in the real world it refuses `long` today).
    sim = simulate("long", seed, ideal=True)
    messages = simulation_messages(sim)
    clock = ScaledClock(messages[0].stamp_ns - 1_000_000_000, rate)
    quiet_ns = int(quiet_period_s * 1e9)
    lock = threading.Lock()
    jobs: list[dict[str, Any]] = []  # in start order
    on_bus: list[tuple[float, str]] = []  # (monotonic s, key)
    holder: dict[str, Daemon] = {}

    def wall_of(scaled_ns: int) -> float:
        """time.monotonic() at which the scaled clock shows scaled_ns."""
        return time.monotonic() - (clock.now_ns() - scaled_ns) / rate / 1e9

    def on_event(event: DaemonEvent) -> None:
        now = time.monotonic()
        with lock:
            if event.kind == "job_started":
                # Called on the ingest thread right after the tracker was found due: its last leave counts.
                snapshot = holder["daemon"].tracker_snapshot(event.camera_id)
                left_ns = snapshot.last_left_received_ns
                quiet_end = wall_of(left_ns + quiet_ns) if left_ns is not None else math.nan
                jobs.append(
                    {
                        "camera_id": event.camera_id,
                        "traversals": event.traversals,
                        "quiet_end_s": quiet_end,
                        "started_s": now,
                        "finished_s": None,
                        "outcome": None,
                        "text": event.text,
                    }
                )
            elif event.kind in ("published", "verified", "refused", "failed", "withdrawn"):
                for job in jobs:
                    if job["camera_id"] == event.camera_id and job["outcome"] is None:
                        job["finished_s"], job["outcome"], job["text"] = now, event.kind, event.text
                        break

    with tempfile.TemporaryDirectory(prefix="rsucal-bench-daemon-") as tmp:
        directory = Path(tmp)
        port = free_loopback_port()
        config = demo_config(sim, directory / "state", port)
        config = config.model_copy(
            update={
                "trigger": config.trigger.model_copy(update={"quiet_period_s": quiet_period_s}),
                "jobs": JobsConfig(max_parallel=1, track_workers=2),
            }
        )
        endpoint = config.zenoh.listen[0]
        stop = threading.Event()
        with daemon_log(directory / "daemon.log") as log_tally:
            daemon = holder["daemon"] = Daemon(config, clock=clock, on_event=on_event)
            sessions: list[zenoh.Session] = []
            started = time.monotonic()
            try:
                daemon.start()
                from daemon.bus import client_config

                listener = zenoh.open(client_config([endpoint]))
                sessions.append(listener)

                def on_result(sample: zenoh.Sample) -> None:
                    with lock:
                        on_bus.append((time.monotonic(), str(sample.key_expr)))

                listener.declare_subscriber(calibration_key(config.rsu_id, "*"), on_result)
                source = zenoh.open(client_config([endpoint]))
                sessions.append(source)
                feeder = threading.Thread(
                    target=publish_messages,
                    args=(source, messages, clock, stop),
                    name="bench-rsu",
                    daemon=True,
                )
                feeder.start()
                replay_s = (messages[-1].stamp_ns - clock.start_ns) / rate / 1e9
                deadline = time.monotonic() + replay_s + 300.0
                # Done when the replay is over, no job is running or can still become due, and all finished.
                settle_s = (quiet_period_s + config.trigger.exit_grace_s) / rate + 1.0
                while time.monotonic() < deadline:
                    time.sleep(0.2)
                    with lock:
                        pending = any(job["outcome"] is None for job in jobs)
                    if (
                        not feeder.is_alive()
                        and not pending
                        and time.monotonic() > started + replay_s + settle_s
                    ):
                        break
            finally:
                stop.set()
                for session in sessions:
                    session.close()  # type: ignore[no-untyped-call]
                daemon.stop()
    published_jobs = [job for job in jobs if job["outcome"] == "published"]
    for job, (t_s, _) in zip(published_jobs, on_bus, strict=False):
        job["on_bus_s"] = t_s
    rows = []
    for job in jobs:
        on_bus_s = job.get("on_bus_s")
        rows.append(
            {
                "camera_id": job["camera_id"],
                "traversals": job["traversals"],
                "outcome": job["outcome"],
                "start_delay_s": job["started_s"] - job["quiet_end_s"],
                "job_s": (job["finished_s"] - job["started_s"]) if job["finished_s"] is not None else None,
                "to_result_s": (job["finished_s"] - job["quiet_end_s"])
                if job["finished_s"] is not None
                else None,
                "to_bus_s": (on_bus_s - job["quiet_end_s"]) if on_bus_s is not None else None,
                "text": job["text"],
            }
        )
    on_bus_latencies = [row["to_bus_s"] for row in rows if row["to_bus_s"] is not None]
    result_latencies = [row["to_result_s"] for row in rows if row["to_result_s"] is not None]
    return {
        "preset": "long",
        "seed": seed,
        "rate": rate,
        "quiet_period_s": quiet_period_s,
        "messages": len(messages),
        "jobs": rows,
        "on_bus": len(on_bus),
        "log_levels": dict(log_tally.levels),
        "log_problems": log_tally.problems,
        "max_to_bus_s": max(on_bus_latencies, default=math.nan),
        "max_to_result_s": max(result_latencies, default=math.nan),
        "passed": bool(on_bus_latencies) and max(on_bus_latencies) <= LATENCY_TARGET_S,
    }


def print_latency(r: dict[str, Any]) -> None:
    print(
        f"\n== latency: preset long (seed {r['seed']}, {r['messages']} messages) replayed at {r['rate']:g}x "
        f"into a Daemon, quiet_period_s {r['quiet_period_s']:g}, jobs.track_workers 2"
    )
    header = (
        f"{'camera':<8}{'trav.':>6}{'outcome':>10}{'quiet end -> start s':>22}{'job s':>8}"
        f"{'-> result s':>12}{'-> on bus s':>12}"
    )
    print(header)
    print("-" * len(header))

    def fmt(value: float | None) -> str:
        return "-" if value is None else f"{value:.2f}"

    for row in r["jobs"]:
        print(
            f"{row['camera_id']:<8}{row['traversals']:>6}{row['outcome'] or 'running':>10}"
            f"{fmt(row['start_delay_s']):>22}{fmt(row['job_s']):>8}{fmt(row['to_result_s']):>12}"
            f"{fmt(row['to_bus_s']):>12}"
        )
    for row in r["jobs"]:
        print(f"  {row['camera_id']}: {row['text']}")
    print(
        "  wall seconds; quiet end = the tracker's last leave (our clock) + quiet_period_s; a result that "
        "agrees with the current one re-verifies it and is not put on the bus"
    )
    print(
        f"  every job: quiet-period end -> result stored, max {r['max_to_result_s']:.2f} s (for information)"
    )
    print(
        f"{'PASS' if r['passed'] else 'FAIL'}  quiet-period end -> calibration on the bus "
        f"{r['max_to_bus_s']:.2f} s <= {LATENCY_TARGET_S:g} s ({r['on_bus']} result(s) on the bus)"
    )


# ---------------------------------------------------------------------------------------------- profile


@dataclass
class PySpy:
    """`py-spy record` of a process for a while, all threads, as collapsed stacks."""

    process: subprocess.Popen[bytes]
    output: Path

    @staticmethod
    def start(pid: int, seconds: float, output: Path, gil: bool = False) -> PySpy | None:
        """Record for `seconds`; with `gil` only the thread holding the GIL is sampled."""
        exe = shutil.which("py-spy")
        if exe is None:
            return None
        command = [exe, "record", "--pid", str(pid), "--duration", str(max(1, int(seconds))), "--rate", "200"]
        command += ["--format", "raw", "--threads", "--nonblocking", "--output", str(output)]
        command += ["--gil"] if gil else []
        process = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        return PySpy(process, output)

    def finish(self) -> dict[str, Any]:
        try:
            _, err = self.process.communicate(timeout=30.0)
        except subprocess.TimeoutExpired:
            self.process.kill()
            _, err = self.process.communicate()
        if not self.output.exists():
            return {"error": err.decode(errors="replace")[-500:]}
        return summarise_collapsed(self.output.read_text())


def _function(frame: str) -> str:
    """`Decoder.decode (daemon/ingest.py:263)` -> `Decoder.decode (daemon/ingest.py)`: lines summed."""
    name, _, where = frame.partition(" (")
    return f"{name} ({where.rsplit(':', 1)[0]})" if where else name


def summarise_collapsed(text: str, top: int = 16) -> dict[str, Any]:
    """Samples per thread and the functions with the most samples, self (leaf) and total (anywhere on stack);
    py-spy's collapsed stacks: `thread (tid);outer frame;...;leaf frame COUNT`."""
    threads: Counter[str] = Counter()
    leaf: Counter[str] = Counter()
    inclusive: Counter[str] = Counter()
    total = 0
    for line in text.splitlines():
        stack, _, count_text = line.rpartition(" ")
        if not stack or not count_text.isdigit():
            continue
        count = int(count_text)
        thread, *frames = stack.split(";")
        frames = [_function(frame) for frame in frames]
        total += count
        threads[thread.split(": ", 1)[-1] if ": " in thread else thread] += count
        if frames:
            leaf[frames[-1]] += count
        for name in set(frames):
            if not name.startswith(("Thread.", "_bootstrap")):
                inclusive[name] += count
    return {
        "samples": total,
        "threads": threads.most_common(8),
        "self": leaf.most_common(top),
        "total": inclusive.most_common(top + 10),
    }


def print_py_spy(summary: dict[str, Any], what: str = "the threads that were not idle") -> None:
    if "error" in summary:
        print(f"  py-spy failed: {summary['error']}")
        return
    total = max(1, summary["samples"])
    print(f"  py-spy of the daemon process ({summary['samples']} samples of {what}):")
    for name, count in summary["threads"]:
        print(f"    {100 * count / total:5.1f} %  {name}")
    print("  functions by samples on top of the stack (self):")
    for name, count in summary["self"]:
        print(f"    {100 * count / total:5.1f} %  {name}")
    print("  functions by samples anywhere on the stack (total):")
    for name, count in summary["total"]:
        print(f"    {100 * count / total:5.1f} %  {name}")


def run_profile(rate: float, step_s: float) -> dict[str, Any]:
    """cProfile of a Daemon's ingest thread and its bus callback's cost, then py-spy of `rsucal daemon`."""
    from daemon.bus import free_loopback_port
    from daemon.main import Daemon

    site = build_site(MIX, THROUGHPUT_PATTERN)
    profiler = cProfile.Profile()
    callback_ns = [0, 0]  # total, calls
    with tempfile.TemporaryDirectory(prefix="rsucal-bench-daemon-") as tmp:
        directory = Path(tmp)
        port = free_loopback_port()
        endpoint = f"tcp/127.0.0.1:{port}"
        config = site_config(site, directory / "state", port)
        publisher = PublisherProcess(site, endpoint)
        with daemon_log(directory / "daemon.log"), contextlib.ExitStack() as stack:
            daemon = Daemon(config)
            # start() hands these bound methods to its thread and to the bus: wrap them on the instance.
            ingest_loop = daemon._ingest_loop
            on_inbound = daemon._on_inbound

            def profiled_ingest_loop() -> None:
                profiler.enable()
                try:
                    ingest_loop()
                finally:
                    profiler.disable()

            def timed_on_inbound(key: str, payload: bytes, received_ns: int) -> None:
                started = time.perf_counter_ns()
                on_inbound(key, payload, received_ns)
                callback_ns[0] += time.perf_counter_ns() - started
                callback_ns[1] += 1

            daemon._ingest_loop = profiled_ingest_loop  # type: ignore[method-assign]
            daemon._on_inbound = timed_on_inbound  # type: ignore[method-assign]
            daemon.start()
            try:
                monitor = Monitor(stack.enter_context(client_session(endpoint)), None)
                publisher.start()
                step = _ceiling_step(monitor, publisher, rate, step_s)
            finally:
                publisher.close()
                daemon.stop()
    stream = io.StringIO()
    stats = pstats.Stats(profiler, stream=stream)
    stats.strip_dirs().sort_stats("tottime").print_stats(22)
    stats.sort_stats("cumulative").print_stats(22)
    calls = max(1, callback_ns[1])
    result: dict[str, Any] = {
        "rate": rate,
        "step": step,
        "messages": step["accepted"],
        "cprofile": stream.getvalue(),
        "callback_us": callback_ns[0] / calls / 1e3,
        "callback_calls": callback_ns[1],
    }
    result["py_spy"] = _py_spy_run(rate, step_s, site) if shutil.which("py-spy") else None
    return result


def _py_spy_run(rate: float, step_s: float, site: Site) -> dict[str, Any] | None:
    with cli_rig(site) as rig:
        spies = [
            PySpy.start(rig.daemon.pid, step_s, rig.directory / f"py-spy-{gil}.txt", gil)
            for gil in (False, True)
        ]
        step = _ceiling_step(rig.monitor, rig.publisher, rate, step_s)
        summaries = [spy.finish() if spy is not None else None for spy in spies]
    summary, gil_summary = summaries
    if summary is not None:
        summary["step"] = step
        summary["gil"] = gil_summary
    return summary


def print_profile(r: dict[str, Any]) -> None:
    step = r["step"]
    print(
        f"\n== profile: a Daemon in this process at {r['rate']:.0f} msg/s for {step['published']} messages "
        f"(published {step['published_rate']:.0f}/s, processed {step['processed_rate']:.0f}/s under cProfile)"
    )
    print(
        f"  bus callback (on Zenoh's thread: Inbound + bounded enqueue): {r['callback_us']:.2f} us per "
        f"message over {r['callback_calls']} calls"
    )
    print("  cProfile of the ingest thread (tottime first, then cumulative):")
    for line in r["cprofile"].splitlines():
        if line.strip():
            print(f"    {line}")
    if r.get("py_spy"):
        spy_step = r["py_spy"]["step"]
        print(
            f"  `rsucal daemon` at {r['rate']:.0f} msg/s without cProfile: published "
            f"{spy_step['published_rate']:.0f}/s, processed {spy_step['processed_rate']:.0f}/s, "
            f"CPU {spy_step['cpu_pct']:.0f} %"
        )
        print_py_spy(r["py_spy"])
        if r["py_spy"].get("gil"):
            print_py_spy(r["py_spy"]["gil"], "the thread holding the GIL (--gil)")


# --------------------------------------------------------------------------------------------- detector


def _street_image(seed: int, width: int = 1920, height: int = 1080) -> Any:
    """A synthetic 8-bit BGR street scene: grey road, sky gradient, coloured boxes, sensor noise (so the
    JPEG is a camera's size, ~0.3-0.6 MB, not a flat picture's)."""
    import numpy as np

    rng = np.random.default_rng(seed)
    image = np.empty((height, width, 3), dtype=np.float32)
    image[:] = np.linspace(200, 90, height, dtype=np.float32)[:, None, None]
    image[height // 2 :] = 95.0
    for _ in range(12):
        x, y = int(rng.integers(0, width - 300)), int(rng.integers(height // 2, height - 150))
        image[y : y + int(rng.integers(60, 150)), x : x + int(rng.integers(120, 300))] = rng.integers(
            0, 256, 3
        )
    image += rng.normal(0.0, 6.0, image.shape)
    return np.clip(image, 0, 255).astype(np.uint8)


def run_detector(seconds: float, cameras: int, fps: float) -> dict[str, Any]:
    import numpy as np
    import zenoh
    from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage

    from daemon.bus import client_config, free_loopback_port
    from daemon.detector import OnnxDetector, decode_output, letterbox, network_input, postprocess
    from daemon.images import decode_compressed_image, encode_compressed_image
    from daemon.keys import image_key
    from daemon.main import Daemon
    from schemas.config import DetectorConfig

    # The test suite's model builder (it needs the `onnx` package of the [test] extra).
    sys.path.insert(0, str(REPO_ROOT / "tests" / "daemon"))
    import onnx
    from onnx_models import add_backbone, build_model

    with tempfile.TemporaryDirectory(prefix="rsucal-bench-detector-") as tmp:
        model, gflops = add_backbone(build_model("yolov8", 640, 640))
        model_path = Path(tmp) / "bench-detector.onnx"
        onnx.save(model, str(model_path))
        detector_config = DetectorConfig(model=model_path, layout="yolov8", threads=1, queue_images=2)
        images = [_street_image(seed) for seed in range(8)]
        payload_sizes = [len(encode_compressed_image(image, 10**18, "c")) for image in images]

        # Per-image cost of each stage, one thread, no bus.
        detector = OnnxDetector(detector_config, None, "bench")
        session_run = detector._session.run  # the stage timing calls the model alone
        stages: dict[str, list[float]] = {
            "jpeg decode": [],
            "letterbox + input": [],
            "onnxruntime": [],
            "decode + NMS": [],
        }
        for i in range(12):
            payload = encode_compressed_image(images[i % len(images)], 10**18 + i, "c")
            t0 = time.perf_counter()
            decoded = decode_compressed_image(payload)
            t1 = time.perf_counter()
            canvas, placement = letterbox(decoded.image, 640, 640, centred=True)
            tensor = network_input(canvas, "yolov8")
            t2 = time.perf_counter()
            (output,) = session_run(None, {"images": tensor})
            t3 = time.perf_counter()
            boxes, scores, classes = decode_output(output, "yolov8", 640, 640)
            postprocess(boxes, scores, classes, placement, 1920, 1080, detector_config, None)
            t4 = time.perf_counter()
            if i >= 2:  # the first runs warm up onnxruntime's allocations
                for name, value in zip(stages, (t1 - t0, t2 - t1, t3 - t2, t4 - t3), strict=True):
                    stages[name].append(value)

        port = free_loopback_port()
        endpoint = f"tcp/127.0.0.1:{port}"
        config = site_config_for_detector(Path(tmp) / "state", port, cameras, detector_config)
        daemon = Daemon(config)
        daemon.start()
        session = zenoh.open(client_config([endpoint]))
        stop = threading.Event()
        sent = [0] * cameras

        def publish(index: int) -> None:
            camera_id = config.cameras[index].camera_id
            publisher = session.declare_publisher(
                image_key(config.rsu_id, camera_id), congestion_control=zenoh.CongestionControl.BLOCK
            )
            encoded = [encode_compressed_image(image, 10**18, camera_id) for image in images]
            start, period = time.monotonic(), 1.0 / fps
            frame = 0
            while not stop.is_set():
                # Re-stamp the pre-encoded image: only the header changes, as for a real camera.
                message = CompressedImage.FromString(encoded[frame % len(encoded)])
                message.timestamp.FromNanoseconds(time.time_ns())
                publisher.put(message.SerializeToString())
                sent[index] += 1
                frame += 1
                delay = start + frame * period - time.monotonic()
                if delay > 0:
                    stop.wait(delay)
            publisher.undeclare()

        try:
            threads = [threading.Thread(target=publish, args=(i,), daemon=True) for i in range(cameras)]
            before = daemon.counters.snapshot()
            usage_before = process_usage(os.getpid())
            started = time.monotonic()
            for thread in threads:
                thread.start()
            stop.wait(seconds)
            stop.set()
            for thread in threads:
                thread.join(10)
            elapsed = time.monotonic() - started
            usage_after = process_usage(os.getpid())
            after = daemon.counters.snapshot()
        finally:
            session.close()
            daemon.stop()
        per_camera = {}
        for index, camera in enumerate(config.cameras):
            name = camera.camera_id

            def delta(counter: str, name: str = name) -> int:
                return after.get(f"images.{name}.{counter}", 0) - before.get(f"images.{name}.{counter}", 0)

            per_camera[name] = {
                "sent": sent[index],
                "received": delta("received"),
                "detected": delta("detected"),
                "dropped": delta("dropped"),
                "frames_per_s": delta("detected") / elapsed,
            }
    cpu_s = usage_after.cpu_s - usage_before.cpu_s
    return {
        "model": f"cell detector + random 3x3 conv backbone, YOLOv8 layout, 640 x 640, {gflops:.1f} GFLOPs",
        "cameras": cameras,
        "fps_offered": fps,
        "seconds": elapsed,
        "jpeg_bytes_mean": float(np.mean(payload_sizes)),
        "stage_ms_median": {name: 1000 * float(np.median(values)) for name, values in stages.items()},
        "per_camera": per_camera,
        "detections_accepted": after.get("detections.accepted", 0) - before.get("detections.accepted", 0),
        "process_cpu_pct": 100.0 * cpu_s / elapsed,
    }


def site_config_for_detector(state_dir: Path, port: int, cameras: int, detector: Any) -> DaemonConfig:
    from schemas.common import CameraIntrinsics, VehicleProfile
    from schemas.config import CalibrationVehicle, CameraConfig, DaemonConfig, StorageConfig, ZenohConfig

    intrinsics = CameraIntrinsics(width=1920, height=1080, fx=1800.0, fy=1800.0, cx=960.0, cy=540.0)
    return DaemonConfig(
        rsu_id="bench",
        zenoh=ZenohConfig(listen=[f"tcp/127.0.0.1:{port}"]),
        cameras=[
            CameraConfig(camera_id=f"cam{i}", intrinsics=intrinsics, detector=detector)
            for i in range(cameras)
        ],
        vehicles=[
            CalibrationVehicle(
                station_id=1,
                profile=VehicleProfile(length=4.8, width=1.9, height=1.5, imu_offset=(1.5, 0.95, 0.3)),
            )
        ],
        storage=StorageConfig(state_dir=state_dir),
    )


def print_detector(r: dict[str, Any]) -> None:
    print(
        f"\n== detector: {r['cameras']} camera(s), {r['fps_offered']:.0f} images/s offered each, "
        f"{r['seconds']:.0f} s"
    )
    print(f"  model: {r['model']}; JPEG 1920 x 1080, mean {r['jpeg_bytes_mean'] / 1e6:.2f} MB")
    stages = ", ".join(f"{name} {ms:.1f} ms" for name, ms in r["stage_ms_median"].items())
    print(f"  per image, one thread (median): {stages}")
    for name, c in r["per_camera"].items():
        print(
            f"  {name}: {c['frames_per_s']:.2f} detector frames/s; sent {c['sent']}, "
            f"received {c['received']}, detected {c['detected']}, dropped {c['dropped']}"
        )
    print(
        f"  DetectionFrames accepted by ingest: {r['detections_accepted']}; "
        f"process CPU {r['process_cpu_pct']:.0f} % (of one core; publishers in this process included)"
    )


# ------------------------------------------------------------------------------------------------- reverify

REVERIFY_TRAVERSALS = 4  # drive-pasts per job: the first calibration, then the re-verification


def run_reverify(seeds: int, ideal: bool, moved: bool = False) -> dict[str, Any]:
    """Re-verifications of a static camera: the moved-camera scene without its move, per seed the daemon's
    job (daemon.jobs.run_job, in this process) on the first four drive-pasts, then on the last four alone
    (as the daemon windows a calibrated camera's next job), judged by daemon.publication.decide. With
    `moved` the scene keeps its move (0.4 m, 0.6 deg after the fourth drive-past): each run must flag it."""
    from daemon.jobs import JobOutcome, JobSpec, new_job_id, run_job
    from daemon.publication import change_limits, decide
    from daemon.recording import write_simulation_mcap
    from daemon.state import CameraState
    from schemas.config import ChangeConfig, GatesConfig
    from schemas.results import CalibrationResult
    from sim.simulate import resolve_config, simulate

    scene = resolve_config("moved-camera")
    if not moved:
        scene = replace(scene, camera_move=None)
    change = ChangeConfig()
    runs: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory(prefix="rsucal-reverify-") as tmp:
        for seed in range(seeds):
            sim = simulate(scene, seed, ideal=ideal)
            mcap = write_simulation_mcap(sim, Path(tmp) / f"seed-{seed}.mcap")
            camera = sim.cameras[0]
            spans: dict[int, tuple[int, int]] = {}
            for frame in sim.ground_truth[camera.camera_id].frames:
                if frame.calib_box is not None and frame.traversal is not None:
                    begin, end = spans.get(frame.traversal, (frame.stamp_ns, frame.stamp_ns))
                    spans[frame.traversal] = (min(begin, frame.stamp_ns), max(end, frame.stamp_ns))
            ordered = [spans[k] for k in sorted(spans)]
            split_ns = (ordered[REVERIFY_TRAVERSALS - 1][1] + ordered[REVERIFY_TRAVERSALS][0]) // 2
            stamps = [m.stamp_ns for m in sim.v2x]

            base = JobSpec(
                job_id="",
                rsu_id=sim.rsu_id,
                camera_id=camera.camera_id,
                intrinsics=camera.intrinsics,
                vehicle=sim.vehicle,
                station_id=sim.station_id,
                # The site's configured offset (the daemon's prior): the truth's clock offset, as in tests.
                time_offset_ns=sim.ground_truth[camera.camera_id].clock_offset_ns,
                crs=sim.origin.crs,
                recordings=(str(mcap),),
                window_start_ns=0,
                window_end_ns=0,
                gates=GatesConfig(),
                seed=0,
                track_workers=1,
                created_at_ns=0,
                config_hash="bench-reverify",
            )

            def job(base: JobSpec, start_ns: int, end_ns: int, created_at_ns: int) -> JobOutcome:
                job_id = new_job_id(base.camera_id, created_at_ns)
                return run_job(
                    replace(
                        base,
                        job_id=job_id,
                        window_start_ns=start_ns,
                        window_end_ns=end_ns,
                        created_at_ns=created_at_ns,
                    )
                )

            created_ns = max(stamps)
            first = job(base, min(stamps) - 10 * 10**9, split_ns, created_ns)
            second = job(base, split_ns + 1, max(stamps) + 10 * 10**9, created_ns + 10**9)
            run: dict[str, Any] = {"seed": seed, "first": None, "second": None, "decision": None}
            current = None
            if first.result_json is not None:
                current = CalibrationResult.model_validate_json(first.result_json)
                run["first"] = current.verdict.status
            if second.result_json is not None:
                run["second"] = CalibrationResult.model_validate_json(second.result_json).verdict.status
            if current is not None and current.verdict.is_accepted:
                state = CameraState(current_result_id=current.result_id, used_until_ns=split_ns)
                decision = decide(
                    second,
                    current,
                    state,
                    change,
                    window_end_ns=max(stamps),
                    started_ns=created_ns,
                    now_ns=created_ns,
                )
                run["decision"] = decision.event
                info = decision.result.change if decision.result is not None else None
                if info is not None:
                    limit_m, limit_deg = change_limits(info)
                    run.update(
                        moved=info.moved,
                        shift_m=info.shift_m,
                        shift_deg=info.shift_deg,
                        limit_m=limit_m,
                        limit_deg=limit_deg,
                        std_m=info.shift_std_m,
                        std_deg=info.shift_std_deg,
                    )
            runs.append(run)
            print(f"    seed {seed}: {json.dumps(run, default=str)}", flush=True)
    compared = [r for r in runs if "moved" in r]
    flagged = [r for r in compared if r["moved"]]
    return {
        "seeds": seeds,
        "ideal": ideal,
        "moved": moved,
        "runs": runs,
        "compared": len(compared),
        "flagged_moved": len(flagged),
        "passed": len(flagged) == len(compared) if moved else not flagged,
    }


def print_reverify(r: dict[str, Any]) -> None:
    world = "ideal" if r["ideal"] else "realistic"
    what = "a moved camera (moved-camera" if r["moved"] else "a static camera (moved-camera without its move"
    print(
        f"\nreverify: {what}, {world} world), {r['seeds']} seeds; "
        f"calibrated on drive-pasts 1-4, re-verified on 5-8 alone"
    )
    print(
        f"  {'seed':>4}  {'first':>8}  {'second':>8}  {'shift m':>8}  {'limit m':>8}  {'std m':>7}  "
        f"{'shift deg':>9}  {'limit deg':>9}  {'std deg':>7}  decision"
    )
    for run in r["runs"]:
        if "moved" in run:
            numbers = (
                f"{run['shift_m']:8.3f}  {run['limit_m']:8.3f}  {run['std_m']:7.3f}  "
                f"{run['shift_deg']:9.3f}  {run['limit_deg']:9.3f}  {run['std_deg']:7.3f}"
            )
        else:
            numbers = f"{'-':>8}  {'-':>8}  {'-':>7}  {'-':>9}  {'-':>9}  {'-':>7}"
        print(
            f"  {run['seed']:>4}  {run['first'] or 'failed':>8}  {run['second'] or 'failed':>8}  {numbers}  "
            f"{run['decision'] or '-'}"
        )
    print(
        f"  compared {r['compared']} of {r['seeds']} (the first fit accepted, the second accepted or refused "
        f"on its precision alone); "
        f"flagged moved: {r['flagged_moved']} (target {r['compared'] if r['moved'] else 0})"
    )


# ------------------------------------------------------------------------------------------------- main

PARTS = ("sustained", "ceiling", "rss", "latency", "detector", "profile", "reverify")
ALL_PARTS = ("sustained", "ceiling", "rss", "latency", "reverify")


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m bench.daemon", description=(__doc__ or "").split("\n")[0]
    )
    parser.add_argument(
        "--part", choices=[*PARTS, "all"], default="all", help="all = all but detector and profile"
    )
    parser.add_argument("--seconds", type=float, default=60.0, help="sustained: seconds of real-time input")
    parser.add_argument(
        "--rates",
        default=",".join(str(r) for r in DEFAULT_RATES),
        help="ceiling: comma-separated messages/s (each then an unpaced step)",
    )
    parser.add_argument("--step-s", type=float, default=10.0, help="ceiling/profile: seconds per rate")
    parser.add_argument(
        "--py-spy-rate", type=float, help="ceiling: py-spy the daemon during this rate's step"
    )
    parser.add_argument(
        "--no-foxglove-views",
        action="store_true",
        help="ceiling: record the raw channels only (storage.foxglove_views false), to compare",
    )
    parser.add_argument("--rss-hours", type=int, default=24, help="rss: simulated hours")
    parser.add_argument("--rss-rate", type=float, default=480.0, help="rss: time acceleration")
    parser.add_argument("--rss-divisor", type=int, default=5, help="rss: message rates divided by this")
    parser.add_argument(
        "--tracemalloc", action="store_true", help="rss: also trace Python allocations (slower; finds leaks)"
    )
    parser.add_argument("--latency-rate", type=float, default=20.0, help="latency: time acceleration")
    parser.add_argument("--quiet-period-s", type=float, default=30.0, help="latency: trigger.quiet_period_s")
    parser.add_argument("--seed", type=int, default=0, help="latency: simulator seed")
    parser.add_argument("--profile-rate", type=float, default=15_000.0, help="profile: messages/s")
    parser.add_argument("--detector-cameras", type=int, default=2, help="detector: cameras with a detector")
    parser.add_argument("--detector-fps", type=float, default=10.0, help="detector: images/s per camera")
    parser.add_argument("--reverify-seeds", type=int, default=20, help="reverify: simulator seeds")
    parser.add_argument(
        "--reverify-real", action="store_true", help="reverify: the realistic world (default: the ideal one)"
    )
    parser.add_argument(
        "--reverify-moved", action="store_true", help="reverify: keep the move (each run must flag it)"
    )
    parser.add_argument("--json", type=Path, help="also write the results here")
    args = parser.parse_args(argv)
    parts = ALL_PARTS if args.part == "all" else (args.part,)
    rates = [float(r) for r in args.rates.split(",") if r.strip()]

    command = "python -m bench.daemon " + " ".join(sys.argv[1:] if argv is None else argv)
    code = tree_state(["daemon", "schemas", "pipeline", "bench"])
    print(f"rsucal daemon benchmark: {command.strip()}")
    print(f"code: {code}")
    print(f"machine: {os.cpu_count()} cores; load average {load_average()} (1/5/15 min) at the start")
    results: dict[str, Any] = {"command": command.strip(), "code": code, "load_average_start": load_average()}
    checks: list[tuple[str, bool]] = []
    for part in parts:
        load_before = load_average()
        started = time.monotonic()
        if part == "sustained":
            result = run_sustained(args.seconds)
            print_sustained(result)
        elif part == "ceiling":
            result = run_ceiling(rates, args.step_s, args.py_spy_rate, not args.no_foxglove_views)
            print_ceiling(result)
        elif part == "rss":
            result = run_rss(args.rss_hours, args.rss_rate, args.rss_divisor, args.tracemalloc)
            print_rss(result)
        elif part == "latency":
            result = run_latency(args.latency_rate, args.quiet_period_s, args.seed)
            print_latency(result)
        elif part == "detector":
            result = run_detector(args.seconds, args.detector_cameras, args.detector_fps)
            print_detector(result)
        elif part == "reverify":
            ideal, moved = not args.reverify_real, args.reverify_moved
            result = run_reverify(args.reverify_seeds, ideal=ideal, moved=moved)
            print_reverify(result)
        else:
            result = run_profile(args.profile_rate, args.step_s)
            print_profile(result)
        result["load_average_before"] = load_before
        result["load_average_after"] = load_average()
        result["wall_s"] = time.monotonic() - started
        print(
            f"  ({part}: {result['wall_s']:.0f} s; load average {load_before} before, "
            f"{result['load_average_after']} after)"
        )
        results[part] = result
        if "passed" in result:
            checks.append((part, bool(result["passed"])))
    results["load_average_end"] = load_average()
    print(
        f"\nload average {load_average()} (1/5/15 min) at the end; "
        f"other processes share the {os.cpu_count()} cores"
    )
    for part, ok in checks:
        print(f"{'PASS' if ok else 'FAIL'}  {part}")
    if args.json:
        args.json.write_text(json.dumps(results, indent=1, default=str))
    return 0 if all(ok for _, ok in checks) else 1


if __name__ == "__main__":
    sys.exit(main())
