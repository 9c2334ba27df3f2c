"""A certificate authority of a test's own, made with the openssl command line: its certificate
(what clients trust), and server certificates it signs for the names and addresses a test's
servers answer on (HAProxy's edge, PostgreSQL, S3); and a PostgreSQL that takes TLS only."""

from __future__ import annotations

import os
import pwd
import shutil
import signal
import subprocess
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass
from ipaddress import ip_address
from pathlib import Path
from typing import Self

from _cluster import Unavailable, free_port, tool, wait_for


@dataclass(frozen=True)
class ServerCertificate:
    cert: Path  # PEM, the leaf
    key: Path  # PEM, unencrypted, mode 0600
    pem: Path  # the leaf, then its key: what HAProxy's `crt` takes


@dataclass(frozen=True)
class Authority:
    """A CA: `ca` is its certificate (PEM), the file clients are told to trust."""

    folder: Path
    ca: Path
    key: Path

    @classmethod
    def make(cls, folder: Path, *, name: str = "jitdyn test CA") -> Authority:
        folder.mkdir(parents=True, exist_ok=True)
        ca, key = folder / "ca.crt", folder / "ca.key"
        _openssl(
            "req", "-x509", "-new", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:P-256", "-nodes",
            "-keyout", str(key), "-out", str(ca), "-days", "2", "-subj", f"/CN={name}",
            "-addext", "basicConstraints=critical,CA:TRUE",
            "-addext", "keyUsage=critical,keyCertSign,cRLSign",
        )  # fmt: skip
        return cls(folder, ca, key)

    def issue(self, name: str, *, hosts: Sequence[str]) -> ServerCertificate:
        """A server certificate for `hosts` (DNS names or IP addresses, in its subjectAltName)."""
        cert, key, request = (self.folder / f"{name}{ext}" for ext in (".crt", ".key", ".csr"))
        names = ",".join(f"IP:{h}" if _is_ip(h) else f"DNS:{h}" for h in hosts)
        extensions = self.folder / f"{name}.ext"
        extensions.write_text(
            f"subjectAltName={names}\nbasicConstraints=CA:FALSE\n"
            "keyUsage=critical,digitalSignature,keyEncipherment\nextendedKeyUsage=serverAuth\n"
        )
        _openssl(
            "req", "-new", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:P-256", "-nodes",
            "-keyout", str(key), "-out", str(request), "-subj", f"/CN={hosts[0]}",
        )  # fmt: skip
        _openssl(
            "x509", "-req", "-in", str(request), "-CA", str(self.ca), "-CAkey", str(self.key),
            "-CAcreateserial", "-out", str(cert), "-days", "2", "-extfile", str(extensions),
        )  # fmt: skip
        key.chmod(0o600)
        pem = self.folder / f"{name}.pem"
        pem.write_bytes(cert.read_bytes() + key.read_bytes())
        pem.chmod(0o600)
        return ServerCertificate(cert, key, pem)


def _is_ip(host: str) -> bool:
    try:
        ip_address(host)
    except ValueError:
        return False
    return True


def _openssl(*args: str) -> None:
    done = subprocess.run([tool("openssl"), *args], check=False, capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(f"openssl {args[0]} failed:\n{done.stderr}")


PG_BIN = Path("/usr/lib/postgresql/15/bin")


@dataclass
class TlsPostgres:
    """A PostgreSQL 15 server of a test's own that takes TCP connections over TLS only (`hostssl`
    in its pg_hba.conf, `ssl=on` with `certificate`): initdb'd in a fresh folder and run as the
    postgres user, superuser `root`, trust authentication. Stopped (fast shutdown) and removed by
    `close()`."""

    port: int
    folder: Path
    process: subprocess.Popen[bytes]

    @classmethod
    def start(cls, certificate: ServerCertificate) -> TlsPostgres:
        if not (PG_BIN / "initdb").exists():
            raise Unavailable(f"PostgreSQL 15's programs are not in {PG_BIN}")
        if os.geteuid() != 0:
            raise Unavailable("running PostgreSQL as the postgres user needs root")
        try:
            owner = pwd.getpwnam("postgres")
        except KeyError:
            raise Unavailable("there is no postgres user") from None
        as_postgres = [
            tool("setpriv"),
            f"--reuid={owner.pw_uid}",
            f"--regid={owner.pw_gid}",
            "--init-groups",
            "--",
        ]
        # Not under pytest's tmp_path: its parents are root's, 0700.
        folder = Path(tempfile.mkdtemp(prefix="jitdyn-pg-"))
        folder.chmod(0o755)
        data = folder / "data"
        for name, source in (("server.crt", certificate.cert), ("server.key", certificate.key)):
            shutil.copyfile(source, folder / name)
            os.chown(folder / name, owner.pw_uid, owner.pw_gid)
        (folder / "server.key").chmod(0o600)
        os.chown(folder, owner.pw_uid, owner.pw_gid)
        done = subprocess.run(
            [*as_postgres, str(PG_BIN / "initdb"), "-D", str(data), "-U", "root", "--auth=trust",
             "--no-sync", "-E", "UTF8", "--locale=C"],
            check=False, capture_output=True, text=True,
        )  # fmt: skip
        if done.returncode != 0:
            shutil.rmtree(folder, ignore_errors=True)
            raise RuntimeError(f"initdb failed:\n{done.stdout}{done.stderr}")
        (data / "pg_hba.conf").write_text("local all all trust\nhostssl all all 127.0.0.1/32 trust\n")
        port = free_port()
        log = (folder / "postgres.log").open("wb")
        process = subprocess.Popen(
            [*as_postgres, str(PG_BIN / "postgres"), "-D", str(data), "-p", str(port), "-k", str(folder),
             "-c", "listen_addresses=127.0.0.1", "-c", "ssl=on", "-c", "fsync=off",
             "-c", f"ssl_cert_file={folder / 'server.crt'}", "-c", f"ssl_key_file={folder / 'server.key'}"],
            stdout=log, stderr=subprocess.STDOUT, start_new_session=True,
        )  # fmt: skip
        log.close()
        server = cls(port, folder, process)
        try:
            wait_for(server._answers, timeout=30, what="PostgreSQL did not answer over TLS")
        except Exception:
            server.close()
            raise
        return server

    @property
    def admin(self) -> str:
        """A libpq conninfo of its superuser, over TLS."""
        return f"host=127.0.0.1 port={self.port} user=root dbname=postgres sslmode=require"

    def _answers(self) -> bool:
        import psycopg

        if self.process.poll() is not None:
            raise RuntimeError(f"PostgreSQL exited:\n{(self.folder / 'postgres.log').read_text()}")
        try:
            with psycopg.connect(self.admin, connect_timeout=2):
                return True
        except psycopg.OperationalError:
            return False

    def close(self) -> None:
        if self.process.poll() is None:
            os.killpg(self.process.pid, signal.SIGINT)  # fast shutdown: clients are disconnected
            try:
                self.process.wait(timeout=20)
            except subprocess.TimeoutExpired:
                os.killpg(self.process.pid, signal.SIGKILL)
                self.process.wait(timeout=10)
        shutil.rmtree(self.folder, ignore_errors=True)

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
