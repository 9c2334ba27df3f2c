"""deploy/kubernetes run as a kubelet runs it, without a kubelet: the Deployment's container in a
network namespace of its own (its pod network), in a mount namespace where the Secret volume, the
emptyDirs and a read-only root are mounted as the kubelet mounts them, as the pod's user
(runAsUser 10001, fsGroup 10001 as a supplementary group, no capabilities), with the environment
the kubelet builds (the image's ENV, then envFrom the ConfigMap and the Secret, then env) and the
image's ENTRYPOINT. Only the cluster's host names change: they point at a PostgreSQL and at moto's
S3, forwarded into the pod's network on the ports the manifests name. Both speak TLS only, with
certificates a CA made here signed for the address the pod reaches them at, and that CA is the
ca-secret.yaml the pod mounts: the ConfigMap's sslmode=verify-full and https are checked for real."""

from __future__ import annotations

import datetime as _dt
import json
import os
import re
import secrets
import shlex
import stat
import subprocess
import sys
from collections.abc import Iterator, Mapping
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import grpc
import psycopg
import pyarrow.parquet as pq
import pytest
import yaml
from _cluster import REPO, MotoS3, NetnsHost, tool, wait_for
from _raw import PENDULUM, RawSession, open_message
from _tls import Authority, TlsPostgres
from grpc_health.v1 import health_pb2, health_pb2_grpc

from jitdyn.key_files import PLACEHOLDER_PREFIX
from jitdyn.v1 import model_registry_pb2, model_registry_pb2_grpc

pytestmark = pytest.mark.postgres

KUBERNETES = REPO / "deploy" / "kubernetes"
DOCKERFILE = REPO / "deploy" / "Dockerfile"
# What the cluster's DNS would answer for the Services the ConfigMap names.
CLUSTER_HOSTS = ("postgres.jitdyn.svc.cluster.local", "minio.jitdyn.svc.cluster.local")
# Environment variable names the kubelet takes from an envFrom source (others are skipped, with an
# event; `api-keys` is one: it reaches the pod as a file only).
_ENV_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")
_LISTENING = re.compile(r"jitdyn listening on (\S+):(\d+) \(")


def _manifest(name: str) -> dict[str, Any]:
    (document,) = [d for d in yaml.safe_load_all((KUBERNETES / name).read_text()) if d]
    return dict(document)


def _image() -> tuple[dict[str, str], list[str], tuple[int, int]]:
    """The final stage's ENV, ENTRYPOINT and USER, as `docker build` bakes them into the image."""
    text = re.sub(r"\\\n", " ", DOCKERFILE.read_text())
    final = text.split("\nFROM ")[-1]
    environment: dict[str, str] = {}
    entrypoint: list[str] = []
    user = (0, 0)
    for line in final.splitlines():
        word, _, rest = line.strip().partition(" ")
        if word == "ENV":
            environment.update(part.split("=", 1) for part in shlex.split(rest))  # type: ignore[arg-type]
        elif word == "ENTRYPOINT":
            entrypoint = json.loads(rest)
        elif word == "USER":
            uid, gid = rest.split(":")
            user = (int(uid), int(gid))
    return environment, entrypoint, user


def operator_secret(*, api_key: str) -> dict[str, str]:
    """secret.yaml's stringData with every placeholder replaced, as an operator does before applying
    it (PostgreSQL here trusts local connections and moto takes any keys, so these are accepted)."""
    values = dict(_manifest("secret.yaml")["stringData"])
    real = {
        "JITDYN_SECRET": secrets.token_hex(32),
        "PGPASSWORD": secrets.token_urlsafe(24),
        "AWS_ACCESS_KEY_ID": "AKIA" + secrets.token_hex(8).upper(),
        "AWS_SECRET_ACCESS_KEY": secrets.token_urlsafe(30),
        "api-keys": f"{api_key} tenant-a\n",
    }
    assert all(v.startswith(PLACEHOLDER_PREFIX) or k not in real for k, v in values.items())
    values.update(real)
    return values


def operator_ca_secret(ca: Path) -> dict[str, str]:
    """ca-secret.yaml's stringData with the CA's certificate in place of the placeholder."""
    values = dict(_manifest("ca-secret.yaml")["stringData"])
    assert values["ca.crt"].startswith(PLACEHOLDER_PREFIX)
    return {**values, "ca.crt": ca.read_text()}


def _pod_environment(
    container: Mapping[str, Any], *, config: Mapping[str, str], secret_values: Mapping[str, Mapping[str, str]]
) -> dict[str, str]:
    """The kubelet's order: the image's ENV, envFrom in the order listed, then env (each wins over
    what came before)."""
    image_env, _, _ = _image()
    environment = {
        "PATH": f"{Path(tool('jitdyn')).parent}:/usr/local/bin:/usr/bin:/bin",
        "HOME": "/var/lib/jitdyn",  # the image user's home (useradd --home-dir)
        "HOSTNAME": "jitdyn-7c9d5b6f4-x2x9q",
        **image_env,
    }
    for source in container.get("envFrom", []):
        ((kind, reference),) = source.items()
        values = config if kind == "configMapRef" else secret_values[reference["name"]]
        environment.update({k: v for k, v in values.items() if _ENV_NAME.fullmatch(k)})
    environment.update({e["name"]: e["value"] for e in container.get("env", [])})
    return environment


def _secret_volume(
    path: Path, volume: Mapping[str, Any], secret: Mapping[str, str], *, fs_group: int
) -> None:
    """A Secret volume as the kubelet's atomic writer lays it out: the files in a timestamped folder,
    `..data` a symlink to it, each item a symlink through `..data`; files root:fsGroup with the
    volume's defaultMode."""
    stamp = _dt.datetime.now(_dt.UTC).strftime("..%Y_%m_%d_%H_%M_%S.%f000")
    path.mkdir(mode=0o755)
    (path / stamp).mkdir(mode=0o755)
    mode = volume["secret"].get("defaultMode", 0o644)
    for item in volume["secret"]["items"]:
        target = path / stamp / item["path"]
        target.write_text(secret[item["key"]])
        os.chown(target, 0, fs_group)
        os.chmod(target, item.get("mode", mode))
        os.symlink(f"..data/{item['path']}", path / item["path"])
    os.symlink(stamp, path / "..data")
    for folder in (path, path / stamp):
        os.chown(folder, 0, fs_group)
        os.chmod(folder, 0o2755)


def _empty_dir(path: Path, *, fs_group: int) -> None:
    path.mkdir()
    os.chown(path, 0, fs_group)
    os.chmod(path, 0o2777)


@contextmanager
def _postgres_for(url: str, *, admin_conninfo: str) -> Iterator[None]:
    """The role and database the ConfigMap's index URL names, made fresh and dropped afterwards."""
    parts = re.fullmatch(r"postgresql\+psycopg://(\w+)@[^/]+/(\w+)(\?.*)?", url)
    assert parts, url
    role, database, _ = parts.groups()
    with psycopg.connect(admin_conninfo, autocommit=True, connect_timeout=3) as admin:
        admin.execute(f'DROP DATABASE IF EXISTS "{database}" WITH (FORCE)')
        if admin.execute("SELECT 1 FROM pg_roles WHERE rolname = %s", (role,)).fetchone() is None:
            admin.execute(f'CREATE ROLE "{role}" LOGIN')
        admin.execute(f'CREATE DATABASE "{database}" OWNER "{role}"')
        try:
            yield
        finally:
            admin.execute(f'DROP DATABASE IF EXISTS "{database}" WITH (FORCE)')


@dataclass
class Pod:
    """The Deployment's container, started; `address` as another pod reaches it."""

    process: subprocess.Popen[bytes]
    log: Path
    address: str

    def log_text(self) -> str:
        return self.log.read_text(errors="replace")


def _blocking_ancestor(path: Path) -> Path | None:
    """The outermost folder above `path` that other users cannot enter (mode without o+x)."""
    for ancestor in reversed(path.parents[:-1]):
        if not ancestor.stat().st_mode & stat.S_IXOTH:
            return ancestor
    return None


def _code_for_everyone(staging: Path) -> list[str]:
    """Mounts that let the pod's user run this interpreter, this checkout and its venv when they lie
    under a folder only root may enter (pyenv in /root, a CI checkout under a 0700 folder), as an
    image's installation is readable by every user: over each such folder, an empty one holding only
    the code."""
    paths = sorted({Path(p).resolve() for p in (sys.base_prefix, sys.prefix, REPO)})
    outermost = [p for p in paths if not any(p != q and p.is_relative_to(q) for q in paths)]
    blocked = {path: folder for path in outermost if (folder := _blocking_ancestor(path))}
    lines = []
    for k, path in enumerate(blocked):
        (staging / str(k)).mkdir(parents=True)
        lines.append(f"mount --bind {shlex.quote(str(path))} {shlex.quote(str(staging / str(k)))}")
    for folder in dict.fromkeys(blocked.values()):
        lines.append(f"mount -t tmpfs -o mode=0755,size=1m tmpfs {shlex.quote(str(folder))}")
    for k, path in enumerate(blocked):
        lines.append(f"mkdir -p {shlex.quote(str(path))}")
        lines.append(f"mount --move {shlex.quote(str(staging / str(k)))} {shlex.quote(str(path))}")
    return lines


def _unreadable_code() -> list[Path]:
    """This checkout's and its interpreters' folders that other users cannot read and enter."""
    paths = {Path(p).resolve() for p in (sys.base_prefix, sys.prefix, REPO)}
    wanted = stat.S_IROTH | stat.S_IXOTH
    return sorted(p for p in paths if p.stat().st_mode & wanted != wanted)


def _mount_script(
    mounts: Mapping[str, tuple[Path, bool]], run_as: list[str], command: list[str], *, staging: Path
) -> str:
    """What the container runtime does in the pod's mount namespace: the root file system read-only
    (readOnlyRootFilesystem), each volume mounted, then the entrypoint as the pod's user."""
    lines = ["set -e", *_code_for_everyone(staging), "mount --bind / /", "mount -o remount,bind,ro /"]
    # A volume mounted over a folder that holds another's source (the /tmp emptyDir over pytest's
    # tmp_path) goes last.
    sources = [source for source, _ in mounts.values()]
    order = sorted(mounts, key=lambda target: any(s.is_relative_to(target) for s in sources))
    for target in order:
        source, read_only = mounts[target]
        lines.append(f"mount --bind {shlex.quote(str(source))} {shlex.quote(target)}")
        # A bind takes its source mount's flags: the read-only root's, until set.
        flag = "ro" if read_only else "rw"
        lines.append(f"mount -o remount,bind,{flag} {shlex.quote(target)}")
    lines.append("exec " + shlex.join([*run_as, *command]))
    return "\n".join(lines)


@contextmanager
def run_pod(
    workdir: Path,
    host: NetnsHost,
    *,
    config: Mapping[str, str],
    secret_values: Mapping[str, Mapping[str, str]],
) -> Iterator[Pod]:
    """deployment.yaml's pod: its volumes made, its container started; stopped afterwards."""
    spec = _manifest("deployment.yaml")["spec"]["template"]["spec"]
    (container,) = spec["containers"]
    context = spec["securityContext"]
    uid, gid, fs_group = context["runAsUser"], context["runAsGroup"], context["fsGroup"]
    assert context["runAsNonRoot"] and uid != 0
    volumes = {v["name"]: v for v in spec["volumes"]}
    mounts: dict[str, tuple[Path, bool]] = {}
    for mount in container["volumeMounts"]:
        source = workdir / "volumes" / mount["name"]
        source.parent.mkdir(exist_ok=True)
        volume = volumes[mount["name"]]
        if "secret" in volume:
            _secret_volume(source, volume, secret_values[volume["secret"]["secretName"]], fs_group=fs_group)
        else:
            _empty_dir(source, fs_group=fs_group)
        mounts[mount["mountPath"]] = (source, bool(mount.get("readOnly")))
    _, entrypoint, _ = _image()
    command = [*(container.get("command") or entrypoint), *container.get("args", [])]
    command[0] = tool(command[0])  # the image's `jitdyn` is this checkout's
    environment = _pod_environment(container, config=config, secret_values=secret_values)
    run_as = [
        tool("setpriv"),
        f"--reuid={uid}",
        f"--regid={gid}",
        f"--groups={fs_group}",
        "--inh-caps=-all",
        "--bounding-set=-all",
        "--no-new-privs",
        "--",
        "env",
        "-i",
        *(f"{k}={v}" for k, v in environment.items()),
    ]
    log = workdir / "pod.log"
    with ExitStack() as stack:
        # The image's folders are 0755 whatever this process's umask (a server run in-process by an
        # earlier test leaves its 077): mount points and the folders over locked parents included.
        stack.callback(os.umask, os.umask(0o022))
        for target in mounts:
            # Mount points must exist on the host's file system, as the image has them.
            if not Path(target).exists():
                Path(target).mkdir(parents=True)
                stack.callback(lambda t=target: Path(t).rmdir())
        script = _mount_script(mounts, run_as, command, staging=workdir / "python")
        with log.open("wb") as out:
            process = subprocess.Popen(
                [*host.prefix, tool("unshare"), "--mount", "--propagation=private", "sh", "-c", script],
                stdout=out,
                stderr=subprocess.STDOUT,
                start_new_session=True,
            )
        stack.callback(_stop_pod, process)
        port = int(environment["JITDYN_ADDRESS"].rsplit(":", 1)[1])
        pod = Pod(process, log, f"{host.peer_ip}:{port}")

        def listening() -> bool:
            if process.poll() is not None:
                raise RuntimeError(f"the pod exited ({process.returncode}):\n{pod.log_text()}")
            return _LISTENING.search(pod.log_text()) is not None

        wait_for(listening, timeout=60, what="the pod did not listen")
        yield pod


def _stop_pod(process: subprocess.Popen[bytes]) -> None:
    if process.poll() is None:
        os.killpg(process.pid, 15)
        try:
            process.wait(timeout=20)
        except subprocess.TimeoutExpired:
            os.killpg(process.pid, 9)
            process.wait(timeout=10)


def _point_at(config: Mapping[str, str], host: NetnsHost) -> dict[str, str]:
    """The ConfigMap with the cluster's host names replaced by the pod network's way to this host."""
    pointed = {}
    for name, value in config.items():
        for cluster_host in CLUSTER_HOSTS:
            value = value.replace(cluster_host, host.host_ip)
        pointed[name] = value
    return pointed


def _probe(pod: Pod, probe: Mapping[str, Any]) -> bool:
    """One of the container's `grpc:` probes, as the kubelet asks it: the pod's IP, the probe's port
    and service (none: ""), its timeoutSeconds (1 s when not given)."""
    address = f"{pod.address.rsplit(':', 1)[0]}:{probe['grpc']['port']}"
    with grpc.insecure_channel(address) as channel:
        try:
            answer = health_pb2_grpc.HealthStub(channel).Check(
                health_pb2.HealthCheckRequest(service=probe["grpc"].get("service", "")),
                timeout=probe.get("timeoutSeconds", 1),
            )
        except grpc.RpcError:
            return False
    return bool(answer.status == health_pb2.HealthCheckResponse.SERVING)


def test_the_deployment_starts_as_a_kubelet_runs_it_and_serves_an_authenticated_session(
    netns_host: NetnsHost, tmp_path: Path
) -> None:
    (container,) = _manifest("deployment.yaml")["spec"]["template"]["spec"]["containers"]
    code = (REPO.resolve(), Path(sys.prefix).resolve())
    hiding = [
        m["mountPath"]
        for m in container["volumeMounts"]
        if any(p.is_relative_to(m["mountPath"]) for p in code)
    ]
    if hiding:
        # An image installs jitdyn outside its volumes; this checkout's would be hidden by one.
        pytest.skip(
            f"this checkout or its venv ({', '.join(map(str, code))}) lies under the pod's {hiding[0]} volume"
        )
    if unreadable := _unreadable_code():
        # The tmpfs over a locked parent folder opens the way, not the folders themselves.
        pytest.skip(f"the pod's user may not read {', '.join(map(str, unreadable))}")
    config = _point_at(_manifest("configmap.yaml")["data"], netns_host)
    index_port = int(re.search(r"@[^:/]+:(\d+)/", config["JITDYN_INDEX_URL"]).group(1))  # type: ignore[union-attr]
    api_key = secrets.token_urlsafe(32)
    # The CA of ca-secret.yaml, and the certificate it signed for where the pod reaches PostgreSQL
    # and S3 (the host's end of the pod network), and for loopback (this test's own connections).
    pki = Authority.make(tmp_path / "pki")
    services = pki.issue("services", hosts=[netns_host.host_ip, "127.0.0.1"])
    secret_values = {"jitdyn": operator_secret(api_key=api_key), "jitdyn-ca": operator_ca_secret(pki.ca)}
    bucket = config["JITDYN_DATA_ROOT"].removeprefix("s3://").split("/", 1)[0]
    with (
        TlsPostgres.start(services) as postgres,
        MotoS3.start(workdir=tmp_path / "moto", tls=(services.cert, services.key, pki.ca)) as store,
        _postgres_for(config["JITDYN_INDEX_URL"], admin_conninfo=postgres.admin),
    ):
        netns_host.forward(index_port, to=postgres.port)
        store.filesystem().create_dir(bucket)
        netns_host.forward(int(config["AWS_ENDPOINT_URL"].rsplit(":", 1)[1]), to=store.port)
        with run_pod(tmp_path, netns_host, config=config, secret_values=secret_values) as pod:
            for kind in ("startupProbe", "readinessProbe", "livenessProbe"):
                wait_for(
                    lambda k=kind: _probe(pod, container[k]), timeout=30, what=f"the {kind} did not pass"
                )
            status = Path(f"/proc/{pod.process.pid}/status").read_text()
            uids = re.search(r"^Uid:\s+(\d+)", status, re.MULTILINE).group(1)  # type: ignore[union-attr]
            groups = re.search(r"^Groups:\s*(.*)$", status, re.MULTILINE).group(1)  # type: ignore[union-attr]
            with grpc.insecure_channel(pod.address) as channel, pytest.raises(grpc.RpcError) as refused:
                model_registry_pb2_grpc.ModelRegistryServiceStub(channel).ListModels(
                    model_registry_pb2.ListModelsRequest(), timeout=10
                )
            assert refused.value.code() == grpc.StatusCode.UNAUTHENTICATED
            session = RawSession(pod.address, open_message(PENDULUM), api_key=api_key)
            for k in range(20):
                session.send(k)
            location = session.close().summary.location
            with psycopg.connect(postgres.admin) as admin:
                tls = admin.execute(
                    "SELECT count(*), bool_and(s.ssl) FROM pg_stat_ssl s JOIN pg_stat_activity a USING (pid) "
                    "WHERE a.usename = 'jitdyn'"
                ).fetchone()
        print(f"pod ran as uid {uids}, groups {groups}; {tls} TLS connections; session stored at {location}")
        assert (uids, groups.split()) == ("10001", ["10001"])
        assert tls is not None and tls[0] >= 1 and tls[1] is True
        assert location.startswith(f"{config['JITDYN_DATA_ROOT']}/frames/")
        table = pq.read_table(location.removeprefix("s3://"), filesystem=store.filesystem(), columns=["seq"])
        assert sorted(set(table.column("seq").to_pylist())) == list(range(20))
