"""A throwaway PostgreSQL cluster for the tests and the store bench: `initdb` in a temporary directory,
`pg_ctl start` on 127.0.0.1 and a free port (its unix socket in that directory too), a fresh database
per test, stopped and deleted at the end. Run as the `postgres` user when this process is root
(PostgreSQL refuses to run as root).

The binaries are Debian's (`/usr/lib/postgresql/<major>/bin`, 15 or newer; `LABRUNNER_PG_BIN` names
another directory). Without them the PG tests skip, unless `LABRUNNER_REQUIRE_PG=1` (set by .ci/run):
then they fail.
"""

from __future__ import annotations

import os
import shutil
import socket
import subprocess
import tempfile
import time
import uuid
from dataclasses import dataclass
from pathlib import Path

SUPERUSER = "labrunner"  # the cluster's superuser: trusted on loopback, the tests' default login
PASSWORD_USER = "lab_pw"  # a role that must give its password (scram-sha-256), for the password tests
PASSWORD = "pw-s3cret-9"
MIN_MAJOR = 15


def pg_bin() -> Path | None:
    """The directory of initdb/pg_ctl (PostgreSQL 15 or newer), or None."""
    given = os.environ.get("LABRUNNER_PG_BIN")
    candidates = [Path(given)] if given else sorted(Path("/usr/lib/postgresql").glob("*/bin"),
                                                    key=lambda p: _major(p), reverse=True)
    for path in candidates:
        if (path / "initdb").is_file() and (given or _major(path) >= MIN_MAJOR):
            return path
    return None


def _major(path: Path) -> int:
    try:
        return int(path.parent.name)
    except ValueError:
        return 0


def required() -> bool:
    return os.environ.get("LABRUNNER_REQUIRE_PG") == "1"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@dataclass
class PgServer:
    bin: Path
    root: Path  # temporary directory: data/ and the socket
    port: int

    @property
    def data(self) -> Path:
        return self.root / "data"

    def url(self, database: str, *, user: str = SUPERUSER, password: str | None = None) -> str:
        auth = user if password is None else f"{user}:{password}"
        return f"postgresql+psycopg://{auth}@127.0.0.1:{self.port}/{database}"

    def _run(self, *cmd: str, check: bool = True) -> subprocess.CompletedProcess[str]:
        if os.geteuid() == 0:  # the server refuses root: its files belong to postgres
            cmd = ("runuser", "-u", "postgres", "--", *cmd)
        return subprocess.run(cmd, capture_output=True, text=True, check=check, timeout=120)

    def sql(self, statement: str, database: str = "postgres") -> list[tuple[object, ...]]:
        """Run one statement as the superuser (autocommit: CREATE DATABASE needs it); the rows, if any."""
        import psycopg

        with psycopg.connect(host="127.0.0.1", port=self.port, user=SUPERUSER, dbname=database,
                             autocommit=True) as conn:
            cur = conn.execute(statement)
            return list(cur.fetchall()) if cur.description else []

    def new_database(self, prefix: str = "t", *, owner: str | None = None, template: str | None = None) -> str:
        """A fresh database's name: empty, or a copy of `template` (which nobody may be connected to)."""
        name = f"{prefix}_{uuid.uuid4().hex[:12]}"
        self.sql(f'CREATE DATABASE "{name}"' + (f' OWNER "{owner}"' if owner else "")
                 + (f' TEMPLATE "{template}"' if template else ""))
        return name

    def terminate(self, database: str) -> int:
        """Kill every backend connected to `database` (as a server crash or restart would drop them)."""
        rows = self.sql(f"SELECT pg_terminate_backend(pid) FROM pg_stat_activity WHERE datname = '{database}' "
                        "AND pid <> pg_backend_pid()")
        return len(rows)

    def start(self) -> None:
        log = self.root / "server.log"
        opts = f"-c listen_addresses=127.0.0.1 -p {self.port} -k {self.root} -c max_connections=200"
        self._run(str(self.bin / "pg_ctl"), "start", "-w", "-t", "60", "-D", str(self.data), "-l", str(log),
                  "-o", opts)

    def stop(self, mode: str = "fast") -> None:
        self._run(str(self.bin / "pg_ctl"), "stop", "-w", "-m", mode, "-D", str(self.data), check=False)

    def destroy(self) -> None:
        self.stop("immediate")
        shutil.rmtree(self.root, ignore_errors=True)


def start_server(*, durable: bool = False) -> PgServer:
    """A new cluster, started. `durable`: fsync on (the bench); the tests switch it off, which loses
    nothing unless the machine itself crashes (a killed server or client loses nothing committed)."""
    bin_dir = pg_bin()
    if bin_dir is None:
        raise RuntimeError(f"PostgreSQL {MIN_MAJOR}+ binaries not found under /usr/lib/postgresql/*/bin "
                           "(Debian: apt-get install postgresql; or set LABRUNNER_PG_BIN)")
    root = Path(tempfile.mkdtemp(prefix="labrunner-pg-"))
    if os.geteuid() == 0:
        shutil.chown(root, "postgres", "postgres")
    server = PgServer(bin_dir, root, _free_port())
    pwfile = root / "pw"
    pwfile.write_text("unused\n")
    if os.geteuid() == 0:
        shutil.chown(pwfile, "postgres", "postgres")
    server._run(str(bin_dir / "initdb"), "-D", str(server.data), "-U", SUPERUSER, "--auth-local=trust",
                "--auth-host=scram-sha-256", f"--pwfile={pwfile}", "-E", "UTF8", "--locale=C.UTF-8")
    # Loopback: the superuser is trusted; every other role gives its password.
    hba = server.data / "pg_hba.conf"
    hba.write_text(f"local all all trust\nhost all {SUPERUSER} 127.0.0.1/32 trust\n"
                   "host all all 127.0.0.1/32 scram-sha-256\n")
    conf = server.data / "postgresql.conf"
    extra = "" if durable else "fsync = off\nfull_page_writes = off\n"
    with conf.open("a") as fh:
        fh.write(extra)
    for attempt in range(3):
        try:
            server.start()
            break
        except subprocess.CalledProcessError as exc:  # the port was taken meanwhile: another one
            if attempt == 2:
                log = (root / "server.log").read_text() if (root / "server.log").exists() else ""
                server.destroy()
                raise RuntimeError(f"PostgreSQL did not start: {exc.stderr}\n{log[-2000:]}") from None
            server.port = _free_port()
    deadline = time.monotonic() + 30
    while True:
        try:
            server.sql("SELECT 1")
            break
        except Exception:
            if time.monotonic() > deadline:
                server.destroy()
                raise
            time.sleep(0.2)
    server.sql(f"CREATE ROLE {PASSWORD_USER} LOGIN PASSWORD '{PASSWORD}'")
    return server
