"""deploy/grafana/jitdyn.json names only metrics a running server exports: a real `jitdyn serve`
with its metrics endpoint, one session through it, then the scrape against every panel's
queries. It fails when a metric is renamed or dropped without the dashboard."""

from __future__ import annotations

import json
import re
import time
import urllib.request
from pathlib import Path

import pytest

from jitdyn.client import Client, FrameData, SessionOptions

from .test_processes import Serve

DASHBOARD = Path(__file__).resolve().parents[2] / "deploy" / "grafana" / "jitdyn.json"
_SUFFIXES = ("_bucket", "_count", "_sum", "_total", "_created")


def _family(name: str) -> str:
    for suffix in _SUFFIXES:
        name = name.removesuffix(suffix)
    return name


def _metric_names(dashboard: dict[str, object]) -> set[str]:
    return {
        _family(name)
        for panel in dashboard["panels"]  # type: ignore[attr-defined]
        for target in panel["targets"]
        for name in re.findall(r"\bjitdyn_[a-z0-9_]+", target["expr"])
    }


def test_every_metric_a_panel_names_is_in_a_servers_scrape(tmp_path: Path) -> None:
    dashboard = json.loads(DASHBOARD.read_text())
    assert dashboard["templating"]["list"][0]["type"] == "datasource"
    names = _metric_names(dashboard)
    assert len(names) >= 10, names
    server = Serve(tmp_path / "data", processes=1, extra=("--metrics-address", "127.0.0.1:0"))
    try:
        deadline = time.monotonic() + 60
        while not any("metrics on" in line for line in server.lines) and time.monotonic() < deadline:
            time.sleep(0.05)
        address = re.search(r"metrics on http://(\S+)/metrics", "".join(server.lines))
        assert address, server.lines
        with Client(server.address, timeout=30) as client:
            session = client.open_session(
                SessionOptions(model_name="pendulum_1", dt=0.05, scenario="PASSIVE")
            )
            for k in range(5):
                session.send_frame(FrameData(seq=k, t=k * 0.05, qpos=[0.2], qvel=[0.0]))
            session.close()
        scraped = urllib.request.urlopen(f"http://{address.group(1)}/metrics", timeout=10).read().decode()
    finally:
        server.stop()
    exported = {_family(n) for n in re.findall(r"^# TYPE (jitdyn_[a-z0-9_]+) ", scraped, re.MULTILINE)}
    missing = sorted(names - exported)
    assert not missing, f"panels name metrics the server does not export: {missing}"
    assert re.search(r'^jitdyn_ticks_total\{.*source="MEASURED"\} 5\.0$', scraped, re.MULTILINE)


@pytest.mark.parametrize("expr", ["rate(jitdyn_no_such_metric_total[1m])"])
def test_the_check_catches_a_metric_no_server_exports(expr: str) -> None:
    names = _metric_names({"panels": [{"targets": [{"expr": expr}]}]})
    assert names == {"jitdyn_no_such_metric"}
