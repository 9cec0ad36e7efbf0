"""A real PostgreSQL (Debian's ``postgresql`` package) for the database tests: ``initdb`` in a temporary folder,
``postgres`` on a free loopback port (its unix socket in that folder too), one fresh database per test, and
everything stopped and removed at the end.

    with PostgresServer() as pg:
        url = pg.create_database()  # postgresql+psycopg://postgres@127.0.0.1:PORT/test_1
        ...
        pg.drop_database(url)

PostgreSQL refuses to run as root: as root, the cluster belongs to the ``postgres`` user that Debian's package
creates (``nobody`` where there is none), and its programs run through ``runuser``.
"""

from __future__ import annotations

import contextlib
import glob
import os
import pwd
import re
import shutil
import signal
import subprocess
import tempfile
from pathlib import Path

from tests.service.procs import Proc, ProcessError, apt_install, free_port, wait_until

BIN_GLOB = "/usr/lib/postgresql/*/bin"  # Debian: one folder per major version
SUPERUSER = "postgres"  # the cluster's superuser (a role, whoever owns the files)
DRIVER = "postgresql+psycopg"
# a throwaway test server: no durability, loopback only, a quiet log
SERVER_SETTINGS = {
    "listen_addresses": "127.0.0.1",
    "fsync": "off",
    "synchronous_commit": "off",
    "full_page_writes": "off",
    "max_connections": "200",
    "log_min_messages": "warning",
}


class PostgresUnavailable(ProcessError):
    """PostgreSQL (or its Python driver) is not installed here and could not be installed."""


def _bin_dir() -> Path | None:
    """The folder of the newest server's ``initdb`` and ``postgres``."""

    def major(folder: str) -> int:
        m = re.search(r"/(\d+)/bin$", folder)
        return int(m.group(1)) if m else 0

    for folder in sorted(glob.glob(BIN_GLOB), key=major, reverse=True):
        if all(os.access(Path(folder) / name, os.X_OK) for name in ("initdb", "postgres")):
            return Path(folder)
    # elsewhere: initdb on PATH, or a link to it (as /usr/local/bin/initdb may be), beside its server
    initdb = shutil.which("initdb")
    if initdb:
        beside = Path(initdb).resolve().parent
        if os.access(beside / "postgres", os.X_OK):
            return beside
    return None


def find_postgres(install: bool = True) -> Path:
    """The folder holding PostgreSQL's ``initdb`` and ``postgres``, installed with apt-get (as root) when missing.

    Raises:
        PostgresUnavailable: not found and not installable here.
    """
    found = apt_install(["postgresql"], _bin_dir) if install else _bin_dir()
    if found is None:
        raise PostgresUnavailable(
            "PostgreSQL is not installed and could not be installed (as root: apt-get install postgresql)"
        )
    return found


def _server_user() -> str | None:
    """Who runs the server: None (this user) unless root, then ``postgres`` or else ``nobody``."""
    if os.geteuid() != 0:
        return None
    for name in ("postgres", "nobody"):
        try:
            pwd.getpwnam(name)
        except KeyError:
            continue
        return name
    raise PostgresUnavailable("running as root, and there is neither a postgres nor a nobody user to run PostgreSQL")


class PostgresServer:
    """A PostgreSQL cluster of its own in a temporary folder, served on a free loopback port.

    Args:
        install: install Debian's ``postgresql`` with apt-get when missing (as root).
    """

    def __init__(self, install: bool = True) -> None:
        try:
            import psycopg  # noqa: F401  (the driver SQLAlchemy's postgresql+psycopg URLs use)
        except ImportError:
            raise PostgresUnavailable("psycopg is not installed (pip install 'bonemesh[postgres]')") from None
        self.bin = find_postgres(install)
        self.user = _server_user()
        if self.user is not None and not shutil.which("runuser"):
            raise PostgresUnavailable("running as root without runuser (util-linux) to start PostgreSQL as a user")
        # not under pytest's temporary folders: those are private to this user, and the server runs as another
        self.root = Path(tempfile.mkdtemp(prefix="bonemesh-pg-"))
        self.data = self.root / "data"
        self.socket_dir = self.root / "socket"
        self.socket_dir.mkdir()
        if self.user is not None:
            entry = pwd.getpwnam(self.user)
            for path in (self.root, self.socket_dir):
                os.chown(path, entry.pw_uid, entry.pw_gid)
        self.port = free_port()
        self.proc: Proc | None = None
        self.created = 0
        try:
            self._initdb()
            self.start()
        except BaseException:
            self.close()
            raise

    def _as_user(self, argv: list[str]) -> list[str]:
        return argv if self.user is None else ["runuser", "-u", self.user, "--", *argv]

    def _initdb(self) -> None:
        argv = [str(self.bin / "initdb"), "-D", str(self.data), "-U", SUPERUSER, "--auth=trust"]
        argv += ["--encoding=UTF8", "--no-locale", "--no-sync"]
        out = subprocess.run(
            self._as_user(argv), capture_output=True, text=True, timeout=300, check=False, cwd=self.root
        )
        if out.returncode != 0:
            raise ProcessError(f"initdb failed ({out.returncode}):\n{out.stdout[-3000:]}\n{out.stderr[-3000:]}")

    @property
    def admin_dsn(self) -> str:
        """libpq connection string of the ``postgres`` database, over the unix socket."""
        return f"host={self.socket_dir} port={self.port} user={SUPERUSER} dbname=postgres"

    def url(self, database: str) -> str:
        """SQLAlchemy URL of ``database`` over loopback TCP (as a service would connect)."""
        return f"{DRIVER}://{SUPERUSER}@127.0.0.1:{self.port}/{database}"

    def _up(self) -> bool:
        import psycopg

        assert self.proc is not None
        if not self.proc.alive():
            raise ProcessError(f"postgres exited at start:\n{self.proc.tail()}")
        try:
            with psycopg.connect(self.admin_dsn, connect_timeout=2) as conn:
                conn.execute("SELECT 1")
            return True
        except psycopg.OperationalError:
            return False

    def start(self) -> None:
        """Start the server and wait until it takes connections."""
        argv = [str(self.bin / "postgres"), "-D", str(self.data), "-p", str(self.port), "-k", str(self.socket_dir)]
        for name, value in SERVER_SETTINGS.items():
            argv += ["-c", f"{name}={value}"]
        self.proc = Proc(f"postgres:{self.port}", self._as_user(argv), self.root / "postgres.log", cwd=self.root)
        try:
            wait_until(self._up, 60, "PostgreSQL to take connections", interval=0.1)
        except TimeoutError as exc:
            raise ProcessError(f"{exc}\n{self.proc.tail()}") from None

    def _admin(self, sql: str) -> None:
        import psycopg

        with psycopg.connect(self.admin_dsn, autocommit=True) as conn:
            conn.execute(sql)

    def create_database(self) -> str:
        """A new, empty database (``test_<n>``); returns its SQLAlchemy URL."""
        self.created += 1
        name = f"test_{self.created}"
        self._admin(f'CREATE DATABASE "{name}"')
        return self.url(name)

    def drop_database(self, url: str) -> None:
        """Drop the database of ``url`` (closing whatever is still connected to it)."""
        name = url.rsplit("/", 1)[1]
        self._admin(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)')

    def stop(self) -> None:
        """Fast shutdown (SIGINT: sessions are disconnected), SIGKILL after a grace period."""
        if self.proc is not None:
            self.proc.signal_group(signal.SIGINT)
            with contextlib.suppress(subprocess.TimeoutExpired):
                self.proc.popen.wait(timeout=10)
            self.proc.stop(grace=5)
            self.proc = None

    def close(self) -> None:
        """Stop the server and remove its folder."""
        self.stop()
        shutil.rmtree(self.root, ignore_errors=True)

    def __enter__(self) -> PostgresServer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
