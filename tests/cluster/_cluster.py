"""The real pieces of a jitdyn cluster, each a separate process a test starts and stops: replicas of
`jitdyn serve` on their own loopback addresses and data folders, HAProxy in front of them, moto's
S3 server, a PostgreSQL database of their own, and a host in its own network namespace that a test
can cut off. Every class is a context manager whose `close()` is safe to call twice.

    with Replica.start("r1", host="127.0.0.2", data=tmp / "r1", index_url=url) as replica, \\
            Balancer.start([replica], workdir=tmp) as balancer:
        Client(balancer.address).open_session(...)
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import re
import secrets
import shutil
import signal
import socket
import ssl
import string
import subprocess
import sys
import threading
import time
import urllib.request
import uuid
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Self

from prometheus_client.parser import text_string_to_metric_families

REPO = Path(__file__).resolve().parents[2]
HAPROXY_TEMPLATE = REPO / "deploy" / "haproxy" / "haproxy.cfg"
POSTGRES_SERVER = "postgresql+psycopg://root@127.0.0.1:5432"
POSTGRES_ADMIN = "host=127.0.0.1 port=5432 user=root dbname=test"
# One pseudonym secret for every replica, as the Secret of deploy/kubernetes gives them.
SECRET = secrets.token_hex(32)

_LISTENING = re.compile(r"jitdyn listening on (\S+):(\d+) \(")


class Unavailable(Exception):
    """A piece of the cluster cannot run on this machine; the fixture skips with this reason."""


def tool(name: str) -> str:
    """The path of a program: beside this interpreter first (the venv's console scripts, so the
    versions pyproject.toml pins, not another install's on PATH), then PATH."""
    found = shutil.which(name, path=str(Path(sys.executable).parent)) or shutil.which(name)
    if found is None:
        raise Unavailable(f"{name} is not installed")
    return found


def free_port(host: str = "127.0.0.1") -> int:
    with socket.socket() as sock:
        sock.bind((host, 0))
        return int(sock.getsockname()[1])


def wait_for(predicate: Callable[[], bool], *, timeout: float, what: str, interval: float = 0.05) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return
        time.sleep(interval)
    raise TimeoutError(f"{what} within {timeout} s")


def _stop(process: subprocess.Popen[bytes], *, grace: float) -> None:
    """SIGTERM the process group we started, SIGKILL it after `grace` seconds."""
    if process.poll() is not None:
        return
    with contextlib.suppress(ProcessLookupError):
        os.killpg(process.pid, signal.SIGTERM)
    try:
        process.wait(timeout=grace)
    except subprocess.TimeoutExpired:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(process.pid, signal.SIGKILL)
        process.wait(timeout=10)


@dataclass
class Replica:
    """One `jitdyn serve` process (one server process, one worker) with its own data folder."""

    name: str
    host: str
    port: int
    metrics_port: int
    data: Path
    process: subprocess.Popen[bytes]
    log: Path
    log_start: int = 0  # where this run's lines begin in `log`

    @classmethod
    def start(
        cls,
        name: str,
        *,
        host: str,
        data: Path,
        index_url: str,
        port: int = 0,
        prefix: Sequence[str] = (),
        extra: Sequence[str] = (),
        env: Mapping[str, str] | None = None,
        timeout: float = 60.0,
    ) -> Replica:
        """Start and wait for "listening on". `prefix` runs it inside something (`ip netns exec`);
        `env` adds to its environment (the AWS_* settings of a data root)."""
        data.mkdir(parents=True, exist_ok=True)
        log = data.parent / f"{name}.log"
        metrics_port = free_port(host) if not prefix else 9464
        environment = dict(os.environ, **(env or {}), JITDYN_SECRET=SECRET, PYTHONUNBUFFERED="1")
        environment.pop("JITDYN_SECRET_FILE", None)
        command = [
            *prefix,
            tool("jitdyn"),
            "serve",
            f"--address={host}:{port}",
            f"--data={data}",
            f"--index={index_url}",
            "--processes=1",
            "--workers=1",
            f"--metrics-address={host}:{metrics_port}",
            *extra,
        ]
        # Appended to: a replica restarted under its name keeps its earlier runs' lines above.
        start = log.stat().st_size if log.exists() else 0
        with log.open("ab") as out:
            process = subprocess.Popen(
                command, stdout=out, stderr=subprocess.STDOUT, env=environment, start_new_session=True
            )
        replica = cls(name, host, port, metrics_port, data, process, log, start)
        try:
            wait_for(replica._listening, timeout=timeout, what=f"replica {name} did not listen")
        except TimeoutError:
            replica.close()
            raise RuntimeError(f"replica {name} did not start:\n{log.read_text()}") from None
        return replica

    def _listening(self) -> bool:
        if self.process.poll() is not None:
            raise RuntimeError(f"replica {self.name} exited:\n{self.log.read_text()}")
        match = _LISTENING.search(self.log.read_text()[self.log_start :])
        if match:
            self.port = int(match.group(2))
        return match is not None

    @property
    def address(self) -> str:
        return f"{self.host}:{self.port}"

    def metrics(self) -> dict[str, float]:
        """Its Prometheus metrics, each family's samples summed over labels."""
        with urllib.request.urlopen(f"http://{self.host}:{self.metrics_port}/metrics", timeout=5) as response:
            text = response.read().decode()
        sums: dict[str, float] = {}
        for family in text_string_to_metric_families(text):
            for sample in family.samples:
                sums[sample.name] = sums.get(sample.name, 0.0) + sample.value
        return sums

    def stored_sessions(self) -> list[Path]:
        """The Parquet files of the sessions this replica stored in its own folder."""
        return sorted(self.data.rglob("*.parquet"))

    def kill(self) -> None:
        """kill -9, as a host loses power: no shutdown, no flush."""
        with contextlib.suppress(ProcessLookupError):
            os.killpg(self.process.pid, signal.SIGKILL)
        self.process.wait(timeout=10)

    def close(self) -> None:
        _stop(self.process, grace=15)

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def behind_haproxy(
    start_replica: Callable[..., Replica],
    start_balancer: Callable[..., Balancer],
    folder: Path,
    hosts: Sequence[str],
    *,
    extra: Sequence[str],
) -> tuple[list[Replica], Balancer]:
    """One replica on each of `hosts` behind HAProxy, sharing the data folder `folder` (an inline
    model registered by one loads on the others from there)."""
    replicas = [start_replica(f"r{n}", host, data=folder, extra=list(extra)) for n, host in enumerate(hosts)]
    return replicas, start_balancer(replicas)


def session_owner(replicas: Sequence[Replica]) -> Replica:
    """The live replica with the one open session."""
    holding = [
        r for r in replicas if r.process.poll() is None and r.metrics().get("jitdyn_open_sessions", 0) > 0
    ]
    assert len(holding) == 1, [(r.name, r.metrics().get("jitdyn_open_sessions")) for r in replicas]
    return holding[0]


# The shipped frontend ends TLS. The tests of balancing, failover and resumption run the same
# configuration with this one line cleartext (their clients speak plaintext): nothing else differs.
TLS_BIND = "bind ${JITDYN_LB_BIND} ssl crt ${JITDYN_LB_CERT} alpn h2"
CLEARTEXT_BIND = "bind ${JITDYN_LB_BIND} proto h2"


def render_haproxy(
    replicas: Sequence[Replica], *, bind: str, stats_socket: Path, cert: Path | None = None
) -> str:
    """deploy/haproxy/haproxy.cfg with its placeholders filled: TLS with `cert` (the chain, then
    its key, in one PEM file), else with the cleartext bind."""
    servers = "\n".join(f"    server {r.name} {r.address}" for r in replicas)
    template = HAPROXY_TEMPLATE.read_text()
    assert template.count(TLS_BIND) == 1, "haproxy.cfg's frontend no longer binds as TLS_BIND says"
    if cert is None:
        template = template.replace(TLS_BIND, CLEARTEXT_BIND)
    return string.Template(template).substitute(
        JITDYN_LB_BIND=bind,
        JITDYN_LB_CERT=str(cert),
        JITDYN_LB_STATS_SOCKET=str(stats_socket),
        JITDYN_LB_SERVERS=servers,
    )


@dataclass
class Balancer:
    """HAProxy in the foreground (-db) with the repository's configuration over `replicas`."""

    host: str
    port: int
    stats_socket: Path
    process: subprocess.Popen[bytes]
    log: Path

    @classmethod
    def start(
        cls, replicas: Sequence[Replica], *, workdir: Path, host: str = "127.0.0.1", cert: Path | None = None
    ) -> Balancer:
        """Start and wait until every replica is UP; TLS to clients with `cert` (render_haproxy)."""
        haproxy = tool("haproxy")
        workdir.mkdir(parents=True, exist_ok=True)
        port = free_port(host)
        stats_socket = workdir / "haproxy.sock"
        config = workdir / "haproxy.cfg"
        config.write_text(
            render_haproxy(replicas, bind=f"{host}:{port}", stats_socket=stats_socket, cert=cert)
        )
        check = subprocess.run(
            [haproxy, "-c", "-f", str(config)], check=False, capture_output=True, text=True
        )
        if check.returncode != 0:
            raise RuntimeError(f"haproxy rejects {config}:\n{check.stdout}{check.stderr}")
        log = workdir / "haproxy.log"
        with log.open("wb") as out:
            process = subprocess.Popen(
                [haproxy, "-db", "-f", str(config)],
                stdout=out,
                stderr=subprocess.STDOUT,
                start_new_session=True,
            )
        balancer = cls(host, port, stats_socket, process, log)
        try:
            wait_for(
                lambda: balancer.server_states() == {r.name: "UP" for r in replicas},
                timeout=30,
                what="haproxy did not see every replica UP",
            )
        except Exception:
            balancer.close()
            raise
        return balancer

    @property
    def address(self) -> str:
        return f"{self.host}:{self.port}"

    def command(self, line: str) -> str:
        """One command on HAProxy's admin socket."""
        with socket.socket(socket.AF_UNIX) as sock:
            sock.settimeout(5)
            sock.connect(str(self.stats_socket))
            sock.sendall(line.encode() + b"\n")
            chunks = []
            while chunk := sock.recv(65536):
                chunks.append(chunk)
        return b"".join(chunks).decode()

    def server_states(self) -> dict[str, str]:
        """Each replica's state as the health checks see it: UP, DOWN, or a transition."""
        if self.process.poll() is not None:
            raise RuntimeError(f"haproxy exited:\n{self.log.read_text()}")
        try:
            csv = self.command("show stat")
        except OSError:
            return {}
        header, *rows = csv.lstrip("# ").splitlines()
        columns = header.split(",")
        states = {}
        for row in rows:
            values = dict(zip(columns, row.split(","), strict=False))
            if values.get("pxname") == "jitdyn" and values.get("svname") not in ("BACKEND", None):
                states[values["svname"]] = values["status"]
        return states

    def cpu_seconds(self) -> float:
        """User plus system CPU time HAProxy has used."""
        stat = Path(f"/proc/{self.process.pid}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(stat[11]) + int(stat[12])) / os.sysconf("SC_CLK_TCK")

    def close(self) -> None:
        _stop(self.process, grace=5)

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


@dataclass
class MotoS3:
    """moto's S3-speaking server on a free loopback port (any keys, region us-east-1); https when
    started with a certificate, `ca` being the CA that signed it."""

    port: int
    process: subprocess.Popen[bytes]
    log: Path
    ca: Path | None = None

    @classmethod
    def start(
        cls, *, workdir: Path, port: int | None = None, tls: tuple[Path, Path, Path] | None = None
    ) -> MotoS3:
        """Start on `port` (a free one by default), and wait until it answers. `tls`: (certificate,
        its key, the CA that signed it), to serve https."""
        moto = tool("moto_server")
        workdir.mkdir(parents=True, exist_ok=True)
        port = free_port() if port is None else port
        log = workdir / "moto.log"
        secure = ["--ssl-cert", str(tls[0]), "--ssl-key", str(tls[1])] if tls else []
        with log.open("wb") as out:
            process = subprocess.Popen(
                [moto, "-H", "127.0.0.1", "-p", str(port), *secure],
                stdout=out,
                stderr=subprocess.STDOUT,
                start_new_session=True,
            )
        server = cls(port, process, log, tls[2] if tls else None)
        try:
            wait_for(server._answers, timeout=30, what="moto_server did not answer")
        except Exception:
            server.close()
            raise
        return server

    def _answers(self) -> bool:
        if self.process.poll() is not None:
            raise RuntimeError(f"moto_server exited:\n{self.log.read_text()}")
        context = ssl.create_default_context(cafile=str(self.ca)) if self.ca else None
        try:
            with urllib.request.urlopen(f"{self.endpoint_url}/", timeout=1, context=context):
                return True
        except OSError:
            return False

    @property
    def endpoint_url(self) -> str:
        return f"{'https' if self.ca else 'http'}://127.0.0.1:{self.port}"

    def filesystem(self) -> Any:
        """pyarrow's own S3 client on this server, as the replicas make it from AWS_ENDPOINT_URL,
        AWS_REGION and the keys (moto takes any)."""
        import pyarrow.fs as pafs

        return pafs.S3FileSystem(
            endpoint_override=f"127.0.0.1:{self.port}",
            scheme="https" if self.ca else "http",
            tls_ca_file_path=str(self.ca) if self.ca else None,
            access_key="testing",
            secret_key="testing",
            region="us-east-1",
            allow_bucket_creation=True,
        )

    def close(self) -> None:
        _stop(self.process, grace=5)

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


@contextlib.contextmanager
def postgres_database() -> Iterator[str]:
    """A fresh PostgreSQL database for one test run; its SQLAlchemy URL. Dropped afterwards."""
    try:
        import psycopg
    except ImportError as error:
        raise Unavailable(f"psycopg is not installed: {error}") from None
    name = f"jitdyn_cluster_{uuid.uuid4().hex[:12]}"
    try:
        admin = psycopg.connect(POSTGRES_ADMIN, autocommit=True, connect_timeout=3)
    except psycopg.OperationalError as error:
        raise Unavailable(f"PostgreSQL at 127.0.0.1:5432 does not answer: {error}".strip()) from None
    with admin:
        admin.execute(f'CREATE DATABASE "{name}"')
        try:
            yield f"{POSTGRES_SERVER}/{name}"
        finally:
            admin.execute(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)')


class TcpForward:
    """Forwards TCP connections from `listen` to `target`, in a thread: lets a network namespace
    reach a server that listens on the host's loopback only (PostgreSQL here)."""

    def __init__(self, *, listen: tuple[str, int], target: tuple[str, int]) -> None:
        self._target = target
        self._loop = asyncio.new_event_loop()
        self._server = self._loop.run_until_complete(asyncio.start_server(self._accept, *listen))
        self._thread = threading.Thread(target=self._loop.run_forever, name="tcp-forward", daemon=True)
        self._thread.start()

    async def _accept(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            upstream_reader, upstream_writer = await asyncio.open_connection(*self._target)
        except OSError:
            writer.close()
            return
        await asyncio.gather(self._pipe(reader, upstream_writer), self._pipe(upstream_reader, writer))

    @staticmethod
    async def _pipe(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            while data := await reader.read(65536):
                writer.write(data)
                await writer.drain()
        except OSError:
            pass
        finally:
            writer.close()

    def close(self) -> None:
        if self._loop.is_closed():
            return

        async def stop() -> None:
            self._server.close()
            for task in asyncio.all_tasks():
                if task is not asyncio.current_task():
                    task.cancel()

        asyncio.run_coroutine_threadsafe(stop(), self._loop).result(timeout=5)
        self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join(timeout=5)
        self._loop.close()


def _ip(*args: str) -> None:
    result = subprocess.run(["ip", *args], check=False, capture_output=True, text=True)
    if result.returncode != 0:
        raise RuntimeError(f"ip {' '.join(args)}: {result.stderr.strip()}")


class NetnsHost:
    """A host of its own: a network namespace joined to this one by a veth pair on a /30, so a
    test can cut it off (`cut()`: the link goes down; the processes inside run on, unreachable).
    The namespace reaches the host's PostgreSQL through a forward on the host's side of the pair."""

    def __init__(self) -> None:
        tool("ip")
        if os.geteuid() != 0:
            raise Unavailable("network namespaces need root")
        tag = uuid.uuid4().hex[:6]
        self.namespace = f"jitdyn-{tag}"
        self.host_link, self.peer_link = f"jd{tag}h", f"jd{tag}n"
        subnet = 1 + int(tag, 16) % 250
        self.host_ip, self.peer_ip = f"10.231.{subnet}.1", f"10.231.{subnet}.2"
        self._forwards: list[TcpForward] = []
        self._closed = False
        try:
            _ip("netns", "add", self.namespace)
        except RuntimeError as error:
            raise Unavailable(f"cannot make a network namespace here: {error}") from None
        try:
            _ip("link", "add", self.host_link, "type", "veth", "peer", "name", self.peer_link)
            _ip("link", "set", self.peer_link, "netns", self.namespace)
            _ip("addr", "add", f"{self.host_ip}/30", "dev", self.host_link)
            _ip("link", "set", self.host_link, "up")
            inside = ("netns", "exec", self.namespace, "ip")
            _ip(*inside, "addr", "add", f"{self.peer_ip}/30", "dev", self.peer_link)
            _ip(*inside, "link", "set", self.peer_link, "up")
            _ip(*inside, "link", "set", "lo", "up")
        except Exception:
            self.close()
            raise

    @property
    def prefix(self) -> tuple[str, ...]:
        """What runs a command inside the namespace."""
        return (tool("ip"), "netns", "exec", self.namespace)

    def forward(self, port: int, *, to: int | None = None) -> str:
        """Make the host's 127.0.0.1:`to` (default: `port`) reachable from inside as
        host_ip:`port`; returns it."""
        target = ("127.0.0.1", port if to is None else to)
        self._forwards.append(TcpForward(listen=(self.host_ip, port), target=target))
        return f"{self.host_ip}:{port}"

    def cut(self) -> None:
        """Take the host's end of the link down: the namespace is unreachable both ways."""
        _ip("link", "set", self.host_link, "down")

    def restore(self) -> None:
        _ip("link", "set", self.host_link, "up")

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        for forward in self._forwards:
            forward.close()
        # Deleting the namespace deletes the veth pair with it.
        subprocess.run(["ip", "netns", "del", self.namespace], check=False, capture_output=True)
        subprocess.run(["ip", "link", "del", self.host_link], check=False, capture_output=True)

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


__all__ = [
    "Balancer",
    "MotoS3",
    "NetnsHost",
    "Replica",
    "TcpForward",
    "Unavailable",
    "free_port",
    "postgres_database",
    "render_haproxy",
    "tool",
    "wait_for",
]
