"""A throwaway PostgreSQL server for tests: initdb into a temporary folder, started on a free local
port with the installed binaries (PostgreSQL 15 on our machines), stopped and removed afterwards.
Run as root, the server runs as the 'postgres' user (initdb refuses root). Without the binaries or
psycopg the tests that need it skip, unless MORPHOPT_REQUIRE_POSTGRES=1 (.ci/run) makes that a
failure."""

import contextlib
import os
import pathlib
import pwd
import shutil
import socket
import subprocess
import tempfile

import pytest


def _binary(name: str) -> str | None:
    found = shutil.which(name)
    if found:
        return found
    for folder in sorted(pathlib.Path("/usr/lib/postgresql").glob("*/bin"), reverse=True):
        if (folder / name).exists():
            return str(folder / name)
    return None


def _missing(reason: str):
    if os.environ.get("MORPHOPT_REQUIRE_POSTGRES") == "1":
        pytest.fail(f"PostgreSQL is required here (MORPHOPT_REQUIRE_POSTGRES=1): {reason}")
    pytest.skip(reason)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@contextlib.contextmanager
def throwaway_postgres():
    """An SQLAlchemy URL (postgresql+psycopg://) of a fresh, empty PostgreSQL server, removed on exit;
    RuntimeError naming what is missing (psycopg, the server binaries, a user to run them as root)."""
    try:
        import psycopg  # noqa: F401
    except ImportError as exc:
        raise RuntimeError("psycopg is not installed (pip install \"morphopt[cluster]\")") from exc
    initdb, pg_ctl = _binary("initdb"), _binary("pg_ctl")
    if not (initdb and pg_ctl):
        raise RuntimeError("the PostgreSQL server binaries (initdb, pg_ctl) are not installed")
    run_as = []
    folder = pathlib.Path(tempfile.mkdtemp(prefix="morphopt-pg-"))
    if os.geteuid() == 0:
        try:
            user = pwd.getpwnam("postgres")
        except KeyError as exc:
            raise RuntimeError("running as root and no 'postgres' user to run the server as") from exc
        os.chown(folder, user.pw_uid, user.pw_gid)
        run_as = ["runuser", "-u", "postgres", "--"]
    port = _free_port()
    data = folder / "data"
    try:
        subprocess.run([*run_as, initdb, "-D", str(data), "-A", "trust", "-U", "test"], check=True,
                       capture_output=True)
        subprocess.run([*run_as, pg_ctl, "-D", str(data), "-l", str(folder / "log"), "-w", "start", "-o",
                        f"-p {port} -k {folder} -c listen_addresses=127.0.0.1"], check=True, capture_output=True)
        yield f"postgresql+psycopg://test@127.0.0.1:{port}/postgres"
    finally:
        subprocess.run([*run_as, pg_ctl, "-D", str(data), "-m", "immediate", "stop"], capture_output=True)
        shutil.rmtree(folder, ignore_errors=True)


@pytest.fixture(scope="module")
def postgres_url():
    """throwaway_postgres() for a test module (skipped where it cannot run; see the module docstring)."""
    try:
        server = throwaway_postgres()
        url = server.__enter__()
    except RuntimeError as exc:
        _missing(str(exc))
    try:
        yield url
    finally:
        server.__exit__(None, None, None)
