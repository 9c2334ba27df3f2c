"""scripts/dashboard_preview.py, the command that draws docs/img/dashboard.png: every panel of
deploy/grafana/jitdyn.json, its own PromQL evaluated by a real Prometheus scraping a real `jitdyn
serve` that ran a session, refused one and rejected a frame, returns series. A panel whose query
returns none shows "No data" in Grafana; tests/server/test_grafana.py checks only that the metric
names exist, this checks that the expressions, labels and all, find them."""

from __future__ import annotations

import importlib.util
import json
import math
import shutil
import sys
import time
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest

from jitdyn.client import Client, FrameData, SessionOptions
from jitdyn.vocabulary import RejectReason

ROOT = Path(__file__).resolve().parents[2]


def _load_preview() -> ModuleType:
    spec = importlib.util.spec_from_file_location(
        "dashboard_preview", ROOT / "scripts" / "dashboard_preview.py"
    )
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # its dataclasses look their module up
    spec.loader.exec_module(module)
    return module


preview = _load_preview()


def _lockstep_load(address: str, *, seconds: float) -> None:
    """A pendulum_1 session answering a frame every 50 ms for `seconds`, with one frame sent twice
    (the second rejected DUPLICATE)."""
    with Client(address, timeout=30) as client:
        session = client.open_session(SessionOptions(model_name="pendulum_1", dt=0.05, scenario="PASSIVE"))
        start = time.monotonic()
        k = 0
        while time.monotonic() - start < seconds:
            session.send_frame(FrameData(seq=k, t=k * 0.05, qpos=[0.3 * math.cos(k * 0.05)], qvel=[0.0]))
            if k == 10:
                session.send_frame(FrameData(seq=k, t=k * 0.05, qpos=[0.0], qvel=[0.0]))
            session.poll()
            k += 1
            time.sleep(0.05)
        session.close()


# 16 s: runs with the slow tests (pytest -m slow), to keep CI under 20 minutes.
@pytest.mark.slow
@pytest.mark.skipif(
    shutil.which("prometheus") is None,
    reason="the prometheus binary is not installed (Debian package prometheus; .ci/run installs it)",
)
def test_every_panels_query_returns_series_from_a_scraped_server(tmp_path: Path) -> None:
    dashboard = json.loads(preview.DASHBOARD.read_text())
    with (
        preview.JitdynServer(tmp_path, processes=1) as server,
        preview.Prometheus(tmp_path, targets=[server.metrics_address]) as prometheus,
    ):
        start, scraped = time.time(), prometheus.scraped()
        refusal = preview.refuse_one(server.address)
        assert "1000 Hz" in refusal, refusal
        _lockstep_load(server.address, seconds=5.0)
        time.sleep(2.5 * preview.SCRAPE_INTERVAL)  # the last frames' scrape
        end = time.time()
        assert prometheus.scraped() >= scraped + 6
        panels = preview.evaluate(
            dashboard,
            lambda expr: prometheus.query_range(expr, start=start, end=end, step=1.0),
            step=1.0,
            span=end - start,
        )
        with pytest.raises(preview.PreviewError, match=r"^prometheus refused 'rate\(up\)': .*range vector"):
            prometheus.query_range("rate(up)", start=start, end=end, step=1.0)
    empty = [f"{p.title}: {t.expr}" for p in panels for t in p.empty_targets()]
    assert not empty, "panels whose queries return no series (Grafana: No data):\n" + "\n".join(empty)
    by_title = {p.title: p for p in panels}
    ticks = {s.labels["source"]: s for s in by_title["Ticks answered, by source"].targets[0].series}
    assert sorted(ticks) == ["CORRECTED", "MEASURED", "PREDICTED"]
    # ~100 ticks; rate(...[1m]) divides what a minute holds by the minute, as Grafana shows it.
    assert max(ticks["MEASURED"].values) > 0.5
    rejected = {
        s.labels["reason"]: max(s.values)
        for s in by_title["Ticks shed and frames rejected"].targets[1].series
    }
    assert sorted(rejected) == sorted(RejectReason)  # each at 0 from the start, so that rate() sees the first
    assert [reason for reason, rate in rejected.items() if rate > 0] == ["DUPLICATE"]
    assert max(by_title["Sessions refused (admission)"].targets[0].series[0].values) > 0


@pytest.mark.parametrize(
    ("expr", "sent"),
    [
        ("rate(x_total[$__rate_interval])", "rate(x_total[4s])"),
        ("rate(x_total[${__rate_interval}])", "rate(x_total[4s])"),
        ('sum(up{instance=~"$instance"})[$__range]', 'sum(up{instance=~".*"})[90s]'),
        ('up{job=~"${job:regex}"}', 'up{job=~".*"}'),
        ("rate(x_total[$__interval])", "rate(x_total[1s])"),
        ("rate(x_total[1m])", "rate(x_total[1m])"),
    ],
)
def test_grafana_variables_are_sent_as_grafana_sends_them(expr: str, sent: str) -> None:
    assert preview.substitute(expr, step=1.0, span=90.0) == sent


def test_an_unknown_builtin_variable_is_named() -> None:
    with pytest.raises(preview.PreviewError, match=r"uses \$__nope, which the preview does not know"):
        preview.substitute("rate(x[$__nope])", step=1.0, span=60.0)


@pytest.mark.parametrize(
    ("fmt", "labels", "name"),
    [
        ("p99 {{model}}", {"model": "biped"}, "p99 biped"),
        ("{{ instance }} process {{process}}", {"instance": "h:1", "process": "0"}, "h:1 process 0"),
        ("", {"__name__": "up", "job": "j"}, 'up{job="j"}'),
    ],
)
def test_legends_follow_legend_format(fmt: str, labels: dict[str, str], name: str) -> None:
    assert preview.legend(fmt, labels) == name


@pytest.mark.parametrize(
    ("value", "unit", "text"),
    [
        (0.0023, "s", "2.3 ms"),
        (0.00042, "s", "420 µs"),
        (0.0, "s", "0 s"),
        (1.5, "ops", "1.5 ops/s"),
        (2500.0, "ops", "2.5K ops/s"),
        (3.0, "short", "3"),
        (12000.0, "short", "12 K"),
        (math.nan, "short", "NaN"),
    ],
)
def test_values_are_shown_in_the_panels_unit(value: float, unit: str, text: str) -> None:
    assert preview.format_value(value, unit) == text


def _panel(kind: str, x: int, y: int, unit: str = "s") -> dict[str, object]:
    return {
        "type": kind,
        "title": kind,
        "gridPos": {"x": x, "y": y, "w": 12, "h": 8},
        "fieldConfig": {"defaults": {"unit": unit}},
        "targets": [{"refId": "A", "expr": "x", "legendFormat": "{{le}}"}],
    }


def test_every_panel_kind_is_drawn_at_its_grid_place(tmp_path: Path) -> None:
    """A timeseries, a heatmap of cumulative buckets, a stat and a panel with no data, drawn at
    Grafana's grid size: 16 rows of 30 px and 8 px gaps, 1600 px wide."""
    import matplotlib.image

    times = np.arange(100.0, 160.0)
    cumulative = [np.full(60, 1.0), np.full(60, 3.0), np.linspace(3.0, 9.0, 60)]
    buckets = tuple(
        preview.Series(labels={"le": le}, times=times, values=values)
        for le, values in zip(("0.001", "0.01", "+Inf"), cumulative, strict=True)
    )
    panels = [
        preview.PanelData(panel=_panel(kind, x, y), targets=(preview.TargetData("A", "x", "{{le}}", series),))
        for kind, x, y, series in (
            ("timeseries", 0, 0, buckets),
            ("heatmap", 12, 0, buckets),
            ("stat", 0, 8, buckets[:1]),
            ("timeseries", 12, 8, ()),
        )
    ]
    assert [len(p.empty_targets()) for p in panels] == [0, 0, 0, 1]
    bounds, _, counts = preview._buckets(panels[1].targets[0])
    assert bounds == ["0.001", "0.01", "+Inf"]
    assert counts[:, -1].tolist() == [1.0, 2.0, 6.0]  # per bucket, not cumulative
    out = tmp_path / "dashboard.png"
    preview.draw(panels, title="t", window=(100.0, 160.0), out=out)
    assert matplotlib.image.imread(out).shape[:2] == (2 * 12 + 44 + 16 * 38 - 8, 1600)


def test_overrides_apply_by_name_and_by_regexp() -> None:
    panel = {
        "fieldConfig": {
            "overrides": [
                {
                    "matcher": {"id": "byRegexp", "options": "/rejected .*/"},
                    "properties": [{"id": "a", "value": 1}],
                },
                {
                    "matcher": {"id": "byName", "options": "rejected TOO_OLD"},
                    "properties": [{"id": "a", "value": 2}],
                },
            ]
        }
    }
    assert preview.overrides(panel, "rejected DUPLICATE") == {"a": 1}
    assert preview.overrides(panel, "rejected TOO_OLD") == {"a": 2}
    assert preview.overrides(panel, "shed biped") == {}
