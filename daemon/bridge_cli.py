"""The `rsucal bridge` subcommand's options; kept apart from daemon.bridges so `rsucal --help` stays fast."""

from __future__ import annotations

import argparse
from typing import Any


def _cmd_bridge(args: argparse.Namespace) -> int:
    from daemon.bridges import bridge_main

    return bridge_main(args)


def add_bridge_parser(sub: Any) -> None:
    """The `bridge` subcommand and its two kinds, on the CLI's subparsers."""
    bridge = sub.add_parser(
        "bridge",
        help="publish a V2X stack's CAMs or a detector's boxes as rsucal bus messages (JSON lines in)",
        description="Read JSON lines (a file, or - for stdin) and publish them on the daemon's bus. Bad "
        "lines are counted and named, never fatal; exit 0 at the end of the input. See docs/integration.md.",
    )
    kinds = bridge.add_subparsers(dest="kind", required=True)
    cam = kinds.add_parser("cam", help="ETSI CAM JSON (CAM units) -> V2xPosition on v2x/cam/{station}")
    yolo = kinds.add_parser(
        "yolo", help="a detector's boxes per image -> DetectionFrame on rsu/{rsu}/camera/{cam}/detections"
    )
    yolo.add_argument("--rsu", required=True, help="the daemon's rsu_id")
    yolo.add_argument("--camera", required=True, help="the camera_id the boxes belong to")
    for parser in (cam, yolo):
        parser.add_argument("--input", default="-", help="JSON lines file, or - for stdin (default)")
        parser.add_argument(
            "--connect",
            action="append",
            default=None,
            help="Zenoh endpoint of the daemon or a router (repeatable; default tcp/127.0.0.1:7447)",
        )
        parser.add_argument("--zenoh-config", default=None, help="Zenoh JSON5 base config (TLS, access)")
        parser.add_argument(
            "--wait-s",
            type=float,
            default=5.0,
            help="wait this long for the daemon's subscriber before the first message of a key (default 5)",
        )
        parser.set_defaults(func=_cmd_bridge)
