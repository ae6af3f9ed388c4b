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


def _openssl(*args: str, cwd: Path) -> None:
    subprocess.run(["openssl", *args], check=True, capture_output=True, timeout=60, cwd=cwd)


_LEAF_EXTENSIONS = (
    "basicConstraints=critical,CA:FALSE\nkeyUsage=critical,digitalSignature\n"
    "extendedKeyUsage=serverAuth,clientAuth\nsubjectAltName=DNS:{name}\n"
)


@pytest.fixture(scope="session")
def expired_certs(certs: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """vehicle-4242 signed by OUR CA, but valid only in January 2020 (`openssl ca` sets past dates)."""
    out = tmp_path_factory.mktemp("expired")
    name = "vehicle-4242"
    _openssl(
        "genpkey", "-algorithm", "EC", "-pkeyopt", "ec_paramgen_curve:P-256", "-out", f"{name}.key", cwd=out
    )
    _openssl(
        "req", "-new", "-key", f"{name}.key", "-subj", f"/O=rsucal test/CN={name}", "-out", "req.csr", cwd=out
    )
    (out / "leaf.ext").write_text(_LEAF_EXTENSIONS.format(name=name), encoding="utf-8")
    (out / "ca.cnf").write_text(
        "[ca]\ndefault_ca = test\n[test]\ndatabase = index.txt\nnew_certs_dir = .\nserial = serial\n"
        "default_md = sha256\npolicy = any\nunique_subject = no\n[any]\ncommonName = supplied\n"
        "organizationName = optional\n",
        encoding="utf-8",
    )
    (out / "index.txt").write_text("", encoding="utf-8")
    (out / "serial").write_text("1000\n", encoding="utf-8")
    authority = ["-cert", str(certs / "ca.pem"), "-keyfile", str(certs / "ca.key")]
    dates = ["-startdate", "20200101000000Z", "-enddate", "20200201000000Z"]
    files = ["-in", "req.csr", "-out", f"{name}.pem", "-extfile", "leaf.ext"]
    _openssl("ca", "-batch", "-notext", "-config", "ca.cnf", *authority, *dates, *files, cwd=out)
    return out


@pytest.fixture(scope="session")
def self_signed_certs(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """vehicle-4242 signed by its own key: no CA at all."""
    out = tmp_path_factory.mktemp("self-signed")
    name = "vehicle-4242"
    _openssl(
        "genpkey", "-algorithm", "EC", "-pkeyopt", "ec_paramgen_curve:P-256", "-out", f"{name}.key", cwd=out
    )
    extensions = ["basicConstraints=critical,CA:FALSE", "extendedKeyUsage=serverAuth,clientAuth"]
    extensions.append(f"subjectAltName=DNS:{name}")
    request = [
        "-key",
        f"{name}.key",
        "-subj",
        f"/O=rsucal test/CN={name}",
        "-days",
        "30",
        "-out",
        f"{name}.pem",
    ]
    _openssl(
        "req", "-x509", "-new", *request, *(arg for ext in extensions for arg in ("-addext", ext)), cwd=out
    )
    return out
