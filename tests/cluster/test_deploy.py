"""deploy/ as Kubernetes and Docker will read it, checked offline: every manifest against the
Kubernetes API's own schemas (kubernetes-validate bundles them), the probes and the autoscaler
against what jitdyn serves, every JITDYN_* setting against jitdyn's settings, and the Dockerfile's
form (no Docker engine runs here)."""

from __future__ import annotations

import re
import sys
import tomllib
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import kubernetes_validate
import prometheus_client
import pytest
import yaml

from jitdyn.settings import settings_for
from jitdyn.v1 import dynamics_pb2

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO / "scripts"))
from wheel_smoke import dockerfile_instructions

KUBERNETES = REPO / "deploy" / "kubernetes"
KUBERNETES_VERSION = "1.30"  # the oldest minor still supported by the cloud providers, late 2026
SESSION_SERVICE = dynamics_pb2.DESCRIPTOR.services_by_name["DynamicsService"].full_name
# Read by the server but not `jitdyn serve` flags (JITDYN_SECRET), or by the shared-tier work to
# come (JITDYN_DATA_ROOT).
OTHER_JITDYN_ENV = {"JITDYN_SECRET", "JITDYN_DATA_ROOT"}


def _resources() -> Iterator[tuple[str, dict[str, Any]]]:
    for path in sorted(KUBERNETES.glob("*.yaml")):
        for document in yaml.safe_load_all(path.read_text()):
            if document:
                yield path.name, document


def _one(kind: str, name: str | None = None) -> dict[str, Any]:
    (found,) = [r for _, r in _resources() if r["kind"] == kind and name in (None, r["metadata"]["name"])]
    return found


@pytest.mark.parametrize("version", [KUBERNETES_VERSION, kubernetes_validate.latest_version()])
def test_every_manifest_is_valid_against_the_kubernetes_schemas(version: str) -> None:
    kinds = []
    for name, resource in _resources():
        try:
            kubernetes_validate.validate(resource, version, strict=True)
        except kubernetes_validate.ValidationError as error:
            raise AssertionError(f"{name}: {resource['kind']} {error.path}: {error.message}") from None
        kinds.append(resource["kind"])
    assert sorted(kinds) == sorted(
        [
            "ConfigMap",
            "Deployment",
            "HorizontalPodAutoscaler",
            "Ingress",
            "PodDisruptionBudget",
            "Secret",
            "Secret",
            "Service",
            "Service",
        ]
    )


def test_the_selectors_pick_the_deployments_pods() -> None:
    labels = _one("Deployment")["spec"]["template"]["metadata"]["labels"]
    for name, resource in _resources():
        selector = resource.get("spec", {}).get("selector")
        if selector is None:
            continue
        wanted = selector.get("matchLabels", selector)
        assert wanted.items() <= labels.items(), name
    assert (
        _one("HorizontalPodAutoscaler")["spec"]["scaleTargetRef"]["name"]
        == _one("Deployment")["metadata"]["name"]
    )


def test_probes_ask_jitdyn_grpc_health_on_the_health_port_off_the_event_loop() -> None:
    (container,) = _one("Deployment")["spec"]["template"]["spec"]["containers"]
    ports = {p["name"]: p["containerPort"] for p in container["ports"]}
    environment = {e["name"]: e["value"] for e in container["env"]}
    # The health port is the one jitdyn serves its probes on (--health-address), not the sessions'.
    assert int(environment["JITDYN_HEALTH_ADDRESS"].rsplit(":", 1)[1]) == ports["health"] != ports["grpc"]
    for probe in ("readinessProbe", "livenessProbe", "startupProbe"):
        assert container[probe]["grpc"]["port"] == ports["health"], probe
        # A probe's timeout is not the 1 s default a loaded machine's scheduler can eat.
        assert container[probe]["timeoutSeconds"] >= 2, probe
    # Readiness follows the session service: a draining replica (NOT_SERVING) takes no new sessions.
    assert container["readinessProbe"]["grpc"]["service"] == SESSION_SERVICE
    # Liveness asks the server's own liveness (no service name): whether its event loop runs.
    assert "service" not in container["livenessProbe"]["grpc"]


def test_the_autoscaler_follows_a_metric_jitdyn_exports() -> None:
    from jitdyn.server.transport.metrics import metrics

    metrics()
    exported = {family.name for family in prometheus_client.REGISTRY.collect()}
    pods = [
        m["pods"]["metric"]["name"]
        for m in _one("HorizontalPodAutoscaler")["spec"]["metrics"]
        if m["type"] == "Pods"
    ]
    assert pods and set(pods) <= exported, (pods, sorted(n for n in exported if n.startswith("jitdyn")))


def _environment() -> dict[str, str]:
    """Every environment variable the pod gets, from its env, the ConfigMap and the Secret."""
    (container,) = _one("Deployment")["spec"]["template"]["spec"]["containers"]
    environment = {e["name"]: e["value"] for e in container["env"]}
    environment.update(_one("ConfigMap")["data"])
    environment.update(_one("Secret", "jitdyn")["stringData"])
    return environment


def test_every_jitdyn_setting_the_pod_gets_is_one_jitdyn_serve_reads_and_parses() -> None:
    settings = {s.env: s for s in settings_for("serve")}
    environment = _environment()
    for name, value in environment.items():
        if not name.startswith("JITDYN_") or name in OTHER_JITDYN_ENV:
            continue
        assert name in settings, f"{name} is not a setting of jitdyn serve"
        settings[name].parse(value)
    # A non-loopback address needs TLS and keys or JITDYN_INSECURE; keys stay required.
    assert settings["JITDYN_INSECURE"].parse(environment["JITDYN_INSECURE"]) is True
    assert environment["JITDYN_API_KEYS"].startswith("/etc/jitdyn/")
    assert {"AWS_ENDPOINT_URL", "AWS_REGION", "JITDYN_DATA_ROOT", "JITDYN_INDEX_URL"} <= environment.keys()
    assert environment["JITDYN_DATA_ROOT"].startswith("s3://")
    secret = _one("Secret", "jitdyn")["stringData"]
    assert {
        "AWS_ACCESS_KEY_ID",
        "AWS_SECRET_ACCESS_KEY",
        "JITDYN_SECRET",
        "PGPASSWORD",
        "api-keys",
    } <= secret.keys()
    assert not {"AWS_ACCESS_KEY_ID", "AWS_SECRET_ACCESS_KEY", "PGPASSWORD"} & _one("ConfigMap")["data"].keys()


def _instructions() -> list[tuple[str, str]]:
    # scripts/wheel_smoke.py builds the wheel from what these instructions copy (CI runs it).
    return dockerfile_instructions()


def test_the_dockerfile_builds_the_wheel_and_runs_it_as_a_user_on_a_pinned_slim_python() -> None:
    instructions = _instructions()
    (base,) = [v for k, v in instructions if k == "ARG" and v.startswith("PYTHON_IMAGE=")]
    assert re.fullmatch(r"PYTHON_IMAGE=python:3\.11\.\d+-slim-\w+(@sha256:[0-9a-f]{64})?", base), base
    stages = [v for k, v in instructions if k == "FROM"]
    assert stages == ["${PYTHON_IMAGE} AS build", "${PYTHON_IMAGE}"]
    final = instructions[[k for k, _ in instructions].index("FROM", 2) :]
    build = instructions[: len(instructions) - len(final)]
    assert any(k == "RUN" and "pip wheel" in v and "--no-deps" in v for k, v in build)
    assert ("COPY", "--from=build /wheels/ /wheels/") in final
    assert any(k == "RUN" and "pip install" in v and "/wheels/jitdyn-" in v for k, v in final)
    users = [v for k, v in final if k == "USER"]
    assert users and users[-1].split(":")[0] not in ("root", "0")
    assert ("ENTRYPOINT", '["jitdyn", "serve"]') in final
    assert any(k == "EXPOSE" and "50051" in v.split() for k, v in final)
    assert any(k == "ENV" and "JITDYN_ADDRESS=0.0.0.0:50051" in v for k, v in final)


def test_the_dockerfile_copies_every_package_the_wheel_is_built_from() -> None:
    config = tomllib.loads((REPO / "pyproject.toml").read_text())
    folders = {Path(folder).parts[0] for folder in config["tool"]["setuptools"]["package-dir"].values()}
    copied = {
        source.rstrip("/")
        for kind, value in _instructions()
        if kind == "COPY" and not value.startswith("--from")
        for source in value.split()[:-1]
    }
    assert folders | {"pyproject.toml", config["project"]["readme"]} <= copied
    ignored = (REPO / ".dockerignore").read_text().splitlines()
    assert {f"!{name}/" for name in folders} <= set(ignored), (
        "the build context must keep every package folder"
    )


def test_the_ingress_ends_tls_and_sends_grpc_to_the_services_grpc_port() -> None:
    ingress = _one("Ingress")["spec"]
    (tls,) = ingress["tls"]
    (rule,) = ingress["rules"]
    assert tls["secretName"] and rule["host"] in tls["hosts"]
    (path,) = rule["http"]["paths"]
    backend = path["backend"]["service"]
    services = {r["metadata"]["name"]: r for _, r in _resources() if r["kind"] == "Service"}
    ports = {p["name"]: p for p in services[backend["name"]]["spec"]["ports"]}
    # The Service's port that carries gRPC in cleartext HTTP/2, as the replicas serve it.
    assert ports[backend["port"]["name"]]["appProtocol"] == "kubernetes.io/h2c"
    annotations = _one("Ingress")["metadata"]["annotations"]
    assert annotations["nginx.ingress.kubernetes.io/backend-protocol"] == "GRPC"


def test_the_index_and_the_object_store_are_reached_over_tls_checked_against_the_mounted_ca() -> None:
    from urllib.parse import parse_qs, urlsplit

    config = _one("ConfigMap")["data"]
    spec = _one("Deployment")["spec"]["template"]["spec"]
    (container,) = spec["containers"]
    ca_secret = _one("Secret", "jitdyn-ca")
    (volume,) = [v for v in spec["volumes"] if v.get("secret", {}).get("secretName") == "jitdyn-ca"]
    (mount,) = [m for m in container["volumeMounts"] if m["name"] == volume["name"]]
    (item,) = volume["secret"]["items"]
    assert item["key"] in ca_secret["stringData"]
    ca_file = f"{mount['mountPath']}/{item['path']}"
    query = parse_qs(urlsplit(config["JITDYN_INDEX_URL"]).query)
    assert query == {"sslmode": ["verify-full"], "sslrootcert": [ca_file]}, query
    assert config["AWS_ENDPOINT_URL"].startswith("https://")
    assert config["AWS_CA_BUNDLE"] == ca_file
    # Read by the server's group (fsGroup), as the API keys are: 0440.
    assert volume["secret"]["defaultMode"] == 0o440 and mount["readOnly"] is True
