"""tests/deploy: the deployment files (Zenoh configs, Dockerfile, systemd unit, compose) and the secure setup.

The daemon tests' polling helpers are shared, not copied: tests/daemon is put on sys.path so that
`from helpers import free_port, wait_until` works here too, whichever test directories are collected.
"""

import sys
from pathlib import Path

_DAEMON_TESTS = str(Path(__file__).resolve().parents[1] / "daemon")
if _DAEMON_TESTS not in sys.path:
    sys.path.insert(0, _DAEMON_TESTS)
