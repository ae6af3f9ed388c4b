"""tests/deploy: the deployment files (Zenoh configs, Dockerfile, systemd unit, compose) and the secure setup.

The daemon tests' polling helpers are shared, not copied: tests/daemon is put on sys.path so that
`from helpers import free_port, wait_until` works here too, whichever test directories are collected.
The test certificates of the secure setup (test_secure_zenoh.py, test_secure_daemon.py) are made here, once
per run, by the documented script deploy/make-test-certs.sh.
"""

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

_DAEMON_TESTS = str(Path(__file__).resolve().parents[1] / "daemon")
if _DAEMON_TESTS not in sys.path:
    sys.path.insert(0, _DAEMON_TESTS)

MAKE_CERTS = Path(__file__).resolve().parents[2] / "deploy" / "make-test-certs.sh"


def _make_certs(out: Path) -> Path:
    if shutil.which("openssl") is None:
        pytest.fail("openssl is needed to make the test certificates (apt-get install openssl)")
    subprocess.run([str(MAKE_CERTS), str(out)], check=True, capture_output=True, timeout=60)
    return out


@pytest.fixture(scope="session")
def certs(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """CA + identities (rsucal-daemon, rsucal-router, vehicle-4242, rsucal-operator, untrusted-client) made by
    the documented script (openssl, offline)."""
    return _make_certs(tmp_path_factory.mktemp("certs"))


@pytest.fixture(scope="session")
def rogue_certs(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The same names signed by ANOTHER CA: an attacker's own 'rsucal-daemon' or 'vehicle-4242'."""
    return _make_certs(tmp_path_factory.mktemp("rogue"))
