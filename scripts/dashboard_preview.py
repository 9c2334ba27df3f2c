"""Draws docs/img/dashboard.png: deploy/grafana/jitdyn.json as Grafana shows it, from real data.

A real `jitdyn serve` runs real REALTIME demo sessions over an emulated network (and is asked for
one session it must refuse), a real Prometheus scrapes it every second, then each panel's own
PromQL is evaluated through Prometheus' HTTP API (/api/v1/query_range) and drawn with matplotlib
at the dashboard's grid layout, in Grafana's dark style. Grafana itself is not needed (it is not
in Debian); Prometheus is (`apt-get install prometheus`).

    python scripts/dashboard_preview.py      # ~100 s (more while admission refuses), docs/img/dashboard.png
    python scripts/dashboard_preview.py --seconds 20 --out /tmp/dashboard.png

It prints each panel's series, and names the panels whose queries returned none: such a panel
shows "No data" in Grafana too. Every process it starts is stopped on exit, Ctrl-C and errors too.
Why it is built this way: docs/decisions/0133-dashboard-preview.md.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import re
import secrets
import shutil
import signal
import subprocess
import sys
import tempfile
import time
import urllib.error
import urllib.parse
import urllib.request
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from types import FrameType
from typing import Any, Self

import numpy as np

from jitdyn.errors import JitdynError

ROOT = Path(__file__).resolve().parent.parent
DASHBOARD = ROOT / "deploy" / "grafana" / "jitdyn.json"
OUT = ROOT / "docs" / "img" / "dashboard.png"
SCRAPE_INTERVAL = 1.0  # s


class PreviewError(Exception):
    """Something the preview needs did not work; main prints its message as one line."""


# ---------------------------------------------------------------------------------------------
# The panels' queries, as Grafana sends them


@dataclass(frozen=True)
class Series:
    """One series of a range query: its labels, sample times (n,) in Unix seconds and values (n,)."""

    labels: Mapping[str, str]
    times: np.ndarray
    values: np.ndarray


@dataclass(frozen=True)
class TargetData:
    """What one of a panel's targets returned: the expression as sent and its series."""

    ref_id: str
    expr: str
    legend_format: str
    series: tuple[Series, ...]


@dataclass(frozen=True)
class PanelData:
    """A panel of the dashboard with the series of its targets."""

    panel: Mapping[str, Any]
    targets: tuple[TargetData, ...]

    @property
    def title(self) -> str:
        return str(self.panel.get("title", f"panel {self.panel.get('id')}"))

    def empty_targets(self) -> list[TargetData]:
        """The targets that returned no series at all (Grafana: "No data")."""
        return [t for t in self.targets if not t.series]


_BUILTIN = re.compile(r"\$(?:\{(__\w+)\}|(__\w+))")
_VARIABLE = re.compile(r"\$\{(\w+)(?::\w+)?\}|\$(\w+)|\[\[(\w+)\]\]")


def substitute(expr: str, *, step: float, scrape_interval: float = SCRAPE_INTERVAL, span: float) -> str:
    """`expr` with Grafana's variables replaced as Grafana would for a query of `span` seconds at
    `step`: $__interval is the step, $__rate_interval max(step + scrape interval, 4 scrape
    intervals) (Grafana's rule), $__range the span; a dashboard variable ($instance, ${job}) is
    "All", which Grafana sends as the regex `.*` for the `=~` matchers it belongs in."""

    def duration(seconds: float) -> str:
        return f"{max(1, math.ceil(seconds))}s"

    builtins = {
        "__interval": duration(step),
        "__rate_interval": duration(max(step + scrape_interval, 4 * scrape_interval)),
        "__range": duration(span),
        "__interval_ms": str(round(step * 1e3)),
        "__range_s": str(round(span)),
    }

    def builtin(match: re.Match[str]) -> str:
        name = match.group(1) or match.group(2)
        if name not in builtins:
            raise PreviewError(f"the expression {expr!r} uses ${name}, which the preview does not know")
        return builtins[name]

    return _VARIABLE.sub(".*", _BUILTIN.sub(builtin, expr))


def legend(legend_format: str, labels: Mapping[str, str]) -> str:
    """A series' name from a target's legendFormat ("p99 {{model}}"); without one, Grafana's
    default: the labels in braces."""
    if legend_format and legend_format != "__auto":
        return re.sub(r"\{\{\s*(\w+)\s*\}\}", lambda m: labels.get(m.group(1), ""), legend_format).strip()
    inner = ", ".join(f'{k}="{v}"' for k, v in sorted(labels.items()) if k != "__name__")
    return f"{labels.get('__name__', '')}{{{inner}}}"


def evaluate(
    dashboard: Mapping[str, Any], query: Callable[[str], list[Series]], *, step: float, span: float
) -> list[PanelData]:
    """Every panel of `dashboard` with its targets' series; `query` runs one PromQL range query."""
    panels = []
    for panel in dashboard["panels"]:
        targets = []
        for target in panel.get("targets", []):
            if target.get("hide"):
                continue
            expr = substitute(target["expr"], step=step, span=span)
            targets.append(
                TargetData(
                    ref_id=str(target.get("refId", "")),
                    expr=expr,
                    legend_format=str(target.get("legendFormat", "")),
                    series=tuple(query(expr)),
                )
            )
        panels.append(PanelData(panel=panel, targets=tuple(targets)))
    return panels


# ---------------------------------------------------------------------------------------------
# The processes: a server, Prometheus, the load


def _stop(process: subprocess.Popen[bytes], *, grace: float) -> None:
    """SIGTERM the process group we started (each runs in its own session), SIGKILL after `grace`."""
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


def _wait_for_line(
    process: subprocess.Popen[bytes], log: Path, pattern: re.Pattern[str], *, what: str, timeout: float
) -> re.Match[str]:
    """The first match of `pattern` in `log`, which `process` writes; a clear error if it exits or
    takes longer than `timeout`."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        text = log.read_text(errors="replace")
        found = pattern.search(text)
        if found:
            return found
        if process.poll() is not None:
            tail = " | ".join(text.strip().splitlines()[-3:])
            raise PreviewError(f"{what} exited with status {process.returncode}: {tail}")
        time.sleep(0.1)
    raise PreviewError(f"{what} did not start within {timeout:g} s (its log: {log})")


class _Process:
    """A program we started in its own process group, its output in a log file; `close()` stops
    it and is safe to call twice."""

    def __init__(self, command: Sequence[str], *, log: Path, env: Mapping[str, str] | None = None) -> None:
        self.log = log
        with log.open("wb") as out:
            self.process = subprocess.Popen(
                list(command),
                stdout=out,
                stderr=subprocess.STDOUT,
                stdin=subprocess.DEVNULL,
                env=dict(env) if env is not None else None,
                start_new_session=True,  # Ctrl-C reaches us only; we stop them in order
            )

    def close(self, grace: float = 20.0) -> None:
        _stop(self.process, grace=grace)

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class JitdynServer(_Process):
    """`jitdyn serve` on a free loopback port, with its Prometheus endpoint on another."""

    def __init__(self, workdir: Path, *, processes: int) -> None:
        env = dict(os.environ, JITDYN_SECRET=secrets.token_hex(32), PYTHONUNBUFFERED="1")
        env.pop("JITDYN_INDEX_URL", None)
        super().__init__(
            [
                sys.executable,
                "-m",
                "jitdyn.cli",
                "serve",
                "--address",
                "127.0.0.1:0",
                "--metrics-address",
                "127.0.0.1:0",
                "--data",
                str(workdir / "data"),
                "--processes",
                str(processes),
                "--drain-grace",
                "1s",
            ],
            log=workdir / "jitdyn-serve.log",
            env=env,
        )
        try:
            listening = _wait_for_line(
                self.process,
                self.log,
                re.compile(r"listening on (\S+:\d+) \("),
                what="jitdyn serve",
                timeout=90,
            )
            metrics = _wait_for_line(
                self.process,
                self.log,
                re.compile(r"metrics on http://(\S+)/metrics"),
                what="jitdyn serve",
                timeout=30,
            )
        except BaseException:
            self.close()
            raise
        self.address = listening.group(1)
        self.metrics_address = metrics.group(1)


class Prometheus(_Process):
    """Prometheus in the foreground on a free loopback port, scraping `targets` every
    `scrape_interval` seconds into a storage folder under `workdir`."""

    def __init__(
        self, workdir: Path, *, targets: Sequence[str], scrape_interval: float = SCRAPE_INTERVAL
    ) -> None:
        binary = shutil.which("prometheus")
        if binary is None:
            raise PreviewError("the prometheus binary is not installed (Debian: apt-get install prometheus)")
        config = workdir / "prometheus.yml"
        config.write_text(
            json.dumps(  # JSON is YAML
                {
                    "global": {"scrape_interval": f"{scrape_interval:g}s", "evaluation_interval": "15s"},
                    "scrape_configs": [
                        {"job_name": "jitdyn", "static_configs": [{"targets": list(targets)}]}
                    ],
                }
            )
        )
        super().__init__(
            [
                binary,
                f"--config.file={config}",
                f"--storage.tsdb.path={workdir / 'prometheus-data'}",
                "--web.listen-address=127.0.0.1:0",
            ],
            log=workdir / "prometheus.log",
        )
        try:
            found = _wait_for_line(
                self.process,
                self.log,
                re.compile(r'msg="Listening on" address=(\S+)'),
                what="prometheus",
                timeout=30,
            )
            _wait_for_line(
                self.process, self.log, re.compile(r"Server is ready"), what="prometheus", timeout=30
            )
            self.url = f"http://{found.group(1)}"
            # Prometheus holds new targets back about 5 s (its discovery's update interval).
            self.wait_for_scrapes(1, timeout=30)
        except BaseException:
            self.close()
            raise

    def _get(self, path: str, params: Mapping[str, str]) -> Any:
        url = f"{self.url}{path}?{urllib.parse.urlencode(params)}"
        try:
            with urllib.request.urlopen(url, timeout=30) as response:
                body = json.load(response)
        except urllib.error.HTTPError as exc:
            body = json.load(exc)
            raise PreviewError(
                f"prometheus refused {params.get('query', path)!r}: {body.get('error')}"
            ) from None
        if body.get("status") != "success":
            raise PreviewError(f"prometheus answered {body.get('status')}: {body.get('error')}")
        return body["data"]

    def query_range(self, expr: str, *, start: float, end: float, step: float) -> list[Series]:
        """The series of `expr` from `start` to `end` (Unix seconds) every `step` seconds."""
        data = self._get(
            "/api/v1/query_range",
            {"query": expr, "start": f"{start:.3f}", "end": f"{end:.3f}", "step": f"{step:g}"},
        )
        series = []
        for item in data["result"]:
            pairs = np.array([(float(t), float(v)) for t, v in item["values"]], dtype=float).reshape(-1, 2)
            series.append(Series(labels=dict(item["metric"]), times=pairs[:, 0], values=pairs[:, 1]))
        return series

    def scraped(self) -> int:
        """How many scrapes of the targets succeeded so far (samples of `up` equal to 1)."""
        data = self._get("/api/v1/query", {"query": "sum(sum_over_time(up[1h]))"})
        return int(float(data["result"][0]["value"][1])) if data["result"] else 0

    def wait_for_scrapes(self, count: int, *, timeout: float) -> None:
        """Return once `count` scrapes succeeded; PreviewError after `timeout` seconds."""
        deadline = time.monotonic() + timeout
        while (done := self.scraped()) < count:
            if time.monotonic() > deadline or self.process.poll() is not None:
                raise PreviewError(
                    f"prometheus scraped its targets {done} of {count} times in {timeout:g} s (its log: {self.log})"
                )
            time.sleep(0.2)


@dataclass(frozen=True)
class DemoRun:
    """One REALTIME demo session (experiments/demo.py, as `jitdyn demo --server` runs it): a model,
    its scenario and its emulated network (latency and jitter in s, loss a probability)."""

    model: str
    scenario: str
    latency: float
    jitter: float
    loss: float


LOAD: tuple[DemoRun, ...] = (
    DemoRun("pendulum_3", "PASSIVE", 0.035, 0.010, 0.05),
    DemoRun("pendulum_2", "CONTROLLED", 0.020, 0.015, 0.02),
    DemoRun("pendulum_1", "EXTERNAL", 0.005, 0.002, 0.01),
    DemoRun("biped", "CONTROLLED", 0.020, 0.005, 0.02),
)
_RETRY = 2.0  # s between a refused demo's tries


def demo_worker(address: str, run: DemoRun, *, seconds: float, wait: float, seed: int) -> int:
    """One demo session of `seconds`, opened again every few seconds while admission refuses it (a
    machine that other programs keep busy refuses, as it should), for at most `wait` seconds; 0
    once it ran."""
    from jitdyn.errors import ResourceExhausted
    from jitdyn.experiments.demo import DemoSettings, run_demo
    from jitdyn.vocabulary import Scenario

    settings = DemoSettings(
        model=run.model,
        scenario=Scenario[run.scenario],
        seconds=seconds,
        latency=run.latency,
        jitter=run.jitter,
        loss=run.loss,
        seed=seed,
    )
    deadline = time.monotonic() + wait
    while time.monotonic() < deadline:
        try:
            run_demo(address, settings, out=sys.stdout, progress=False)
            return 0
        except ResourceExhausted as exc:
            print(f"refused, trying again in {_RETRY:g} s: {exc}", flush=True)
            time.sleep(_RETRY)
    print(f"{run.model}: refused for {wait:g} s", flush=True)
    return 1


class Load:
    """REALTIME demo sessions of `seconds` against `address`, each in a process of its own (this
    script's demo_worker, waiting up to `wait` seconds to be admitted), started a little apart so
    that their imports do not all land at once."""

    def __init__(
        self, address: str, workdir: Path, *, runs: Sequence[DemoRun], seconds: float, wait: float
    ) -> None:
        self.demos: list[_Process] = []
        try:
            for k, run in enumerate(runs):
                job = {"address": address, "run": run.__dict__, "seconds": seconds, "wait": wait, "seed": k}
                self.demos.append(
                    _Process(
                        [sys.executable, str(Path(__file__).resolve()), "--demo-worker", json.dumps(job)],
                        log=workdir / f"demo-{k}-{run.model}.log",
                        env=dict(os.environ, PYTHONUNBUFFERED="1"),
                    )
                )
                time.sleep(0.5)
        except BaseException:
            self.close()
            raise

    def wait(self, timeout: float) -> list[str]:
        """Wait for every demo to end; the last line of each that did not run."""
        deadline = time.monotonic() + timeout
        failed = []
        for demo in self.demos:
            try:
                code = demo.process.wait(timeout=max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                failed.append(f"{demo.log.name}: still running after {timeout:g} s")
                continue
            if code != 0:
                tail = demo.log.read_text(errors="replace").strip().splitlines()[-1:]
                failed.append(f"{demo.log.name}: exit {code}: {' '.join(tail)}")
        return failed

    def close(self) -> None:
        for demo in self.demos:
            demo.close(grace=10)

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


# One slide joint stepped at 1 kHz: its filter is cheap, but a 1 ms tick's transport alone (about
# 2 ms of CPU) is more than a process's tick budget.
_TOO_FAST = """<mujoco model="fast_slider"><option timestep="0.001"/><worldbody><body>
<joint name="s" type="slide" axis="1 0 0"/><geom type="box" size="0.1 0.1 0.1" mass="2"/>
</body></worldbody></mujoco>"""


def refuse_one(address: str) -> str:
    """Open REALTIME sessions at 1 kHz until the server refuses one, so that the admission
    refusals show; the server's reason. A session that cannot fit alone is refused at once, one
    that can takes the room the next would need (server/runtime/admission.py); admitted ones are
    closed at once."""
    from jitdyn.client import Client, SessionOptions
    from jitdyn.errors import ResourceExhausted

    options = SessionOptions(
        inline_mjcf=_TOO_FAST, inline_name="too_fast", scenario="PASSIVE", dt=0.001, clock="REALTIME"
    )
    with Client(address, timeout=30) as client, contextlib.ExitStack() as admitted:
        for _ in range(3):
            try:
                admitted.callback(client.open_session(options).close)
            except ResourceExhausted as exc:
                return str(exc)
    raise PreviewError(
        "the server admitted three REALTIME sessions at 1 kHz, which should not fit its tick budget"
    )


# ---------------------------------------------------------------------------------------------
# Drawing, in Grafana's dark theme

_CANVAS = "#111217"
_PANEL = "#181b1f"
_BORDER = "#2c2e34"
_TEXT = "#ccccdc"
_WEAK = "#8e8e9e"
_GRID = "#26282e"
# Grafana's classic palette, in its order.
_PALETTE = (
    *("#7EB26D", "#EAB839", "#6ED0E0", "#EF843C", "#E24D42", "#1F78C1", "#BA43A9", "#705DA0"),
    *("#508642", "#CCA300", "#447EBC", "#C15C17", "#890F02", "#0A437C", "#6D1F62", "#584477"),
)
_STAT_GREEN = "#73BF69"
# Grafana's grid: 24 columns, rows 30 px high, 8 px between panels.
_COLUMNS = 24
_ROW = 30
_GAP = 8
_WIDTH = 1600
_PAD = 12
_DPI = 100


def _scaled(value: float, suffixes: Sequence[str], base: float = 1000.0) -> tuple[float, str]:
    scaled, index = value, 0
    while abs(scaled) >= base and index < len(suffixes) - 1:
        scaled /= base
        index += 1
    return scaled, suffixes[index]


def _number(value: float) -> str:
    text = f"{value:.3g}"
    return text if "e" not in text else f"{value:.2e}"


def format_value(value: float, unit: str) -> str:
    """`value` as Grafana shows it in `unit` (the units this dashboard uses: short, ops, s, ms,
    percentunit, none)."""
    if not math.isfinite(value):
        return "NaN" if math.isnan(value) else ("+Inf" if value > 0 else "-Inf")
    if unit in ("s", "ms", "µs", "us"):
        seconds = value * {"s": 1.0, "ms": 1e-3}.get(unit, 1e-6)
        magnitude = abs(seconds)
        for limit, scale, suffix in (
            (1e-6, 1e9, "ns"),
            (1e-3, 1e6, "µs"),
            (1.0, 1e3, "ms"),
            (60.0, 1.0, "s"),
        ):
            if magnitude < limit:
                return f"{_number(seconds * scale)} {suffix}" if seconds else "0 s"
        return f"{_number(seconds / 60)} min"
    if unit == "percentunit":
        return f"{_number(value * 100)}%"
    if unit == "percent":
        return f"{_number(value)}%"
    if unit == "ops":
        scaled, suffix = _scaled(value, ("", "K", "M", "B"))
        return f"{_number(scaled)}{suffix} ops/s"
    if unit == "none":
        return _number(value)
    scaled, suffix = _scaled(value, ("", " K", " Mil", " Bil"))
    return f"{_number(scaled)}{suffix}"


def overrides(panel: Mapping[str, Any], name: str) -> dict[str, Any]:
    """The fieldConfig override properties that apply to the series called `name` (matchers byName
    and byRegexp, later ones winning, as in Grafana)."""
    found: dict[str, Any] = {}
    for override in panel.get("fieldConfig", {}).get("overrides", []):
        matcher = override.get("matcher", {})
        option = str(matcher.get("options", ""))
        if matcher.get("id") == "byName":
            hit = option == name
        elif matcher.get("id") == "byRegexp":
            pattern = (
                option[1:-1]
                if len(option) > 1 and option.startswith("/") and option.endswith("/")
                else option
            )
            hit = re.fullmatch(pattern, name) is not None
        else:
            continue
        if hit:
            found.update({p["id"]: p.get("value") for p in override.get("properties", [])})
    return found


def _unit(panel: Mapping[str, Any]) -> str:
    defaults = panel.get("fieldConfig", {}).get("defaults", {})
    return str(defaults.get("unit") or panel.get("options", {}).get("yAxis", {}).get("unit") or "short")


@dataclass(frozen=True)
class _Box:
    """A panel's place in the figure, in figure fractions (left, bottom, width, height)."""

    left: float
    bottom: float
    width: float
    height: float

    def inset(
        self, left: float, bottom: float, right: float, top: float
    ) -> tuple[float, float, float, float]:
        return (self.left + left, self.bottom + bottom, self.width - left - right, self.height - bottom - top)


def _layout(panels: Sequence[PanelData]) -> tuple[float, float, list[_Box]]:
    """The figure's size in pixels and each panel's box, from the panels' gridPos."""
    column = (_WIDTH - 2 * _PAD + _GAP) / _COLUMNS
    rows = max(p.panel["gridPos"]["y"] + p.panel["gridPos"]["h"] for p in panels)
    height = 2 * _PAD + 44 + rows * (_ROW + _GAP) - _GAP
    boxes = []
    for data in panels:
        grid = data.panel["gridPos"]
        x, y = _PAD + grid["x"] * column, _PAD + 44 + grid["y"] * (_ROW + _GAP)
        w, h = grid["w"] * column - _GAP, grid["h"] * (_ROW + _GAP) - _GAP
        boxes.append(_Box(x / _WIDTH, 1 - (y + h) / height, w / _WIDTH, h / height))
    return _WIDTH, height, boxes


def _style_axes(ax: Any, unit: str) -> None:
    from matplotlib.ticker import FuncFormatter, MaxNLocator

    ax.set_facecolor(_PANEL)
    for spine in ax.spines.values():
        spine.set_visible(False)
    ax.tick_params(colors=_WEAK, labelsize=8, length=0, pad=4)
    ax.grid(True, color=_GRID, linewidth=0.8)
    ax.set_axisbelow(True)
    ax.yaxis.set_major_locator(MaxNLocator(nbins=5, steps=[1, 2, 2.5, 5, 10]))
    ax.yaxis.set_major_formatter(FuncFormatter(lambda v, _: format_value(v, unit)))


def _time_axis(ax: Any, start: float, end: float) -> None:
    """Clock times at a round interval that leaves ~110 px a label, none at the very edges (where
    they would run into the y axis' labels)."""
    import matplotlib.dates as mdates

    ax.set_xlim(_date(start), _date(end))
    width = ax.get_position().width * ax.figure.bbox.width
    span = end - start
    step = next((s for s in (5, 10, 15, 30, 60, 120, 300, 600, 1800) if span / s <= width / 110), 3600)
    margin = 0.04 * span
    first = math.ceil((start + margin) / step) * step
    ax.set_xticks([_date(t) for t in np.arange(first, end - margin, step)])
    ax.xaxis.set_major_formatter(mdates.DateFormatter("%H:%M:%S"))


def _date(seconds: float) -> float:
    return seconds / 86400.0  # matplotlib's dates: days since 1970-01-01


def _draw_timeseries(fig: Any, box: _Box, data: PanelData, window: tuple[float, float]) -> None:
    unit = _unit(data.panel)
    # In the targets' order (A, B, ...), each target's series by name, as Grafana lists them.
    lines = [
        line
        for target in data.targets
        for line in sorted(
            ((legend(target.legend_format, s.labels), s) for s in target.series), key=lambda x: x[0]
        )
    ]
    # Grafana's list legend flows its entries left to right: as many columns as the longest fits.
    entry = 40 + 6.2 * max((len(name) for name, _ in lines), default=0)
    columns = max(1, min(len(lines), int(box.width * fig.bbox.width // entry)))
    rows = max(1, math.ceil(len(lines) / columns))
    ax = fig.add_axes(box.inset(0.052, (26 + 16 * rows) / fig.bbox.height, 0.008, 36 / fig.bbox.height))
    _style_axes(ax, unit)
    for k, (name, series) in enumerate(lines):
        style = overrides(data.panel, name)
        line, colour = style.get("custom.lineStyle") or {}, style.get("color") or {}
        ax.plot(
            [_date(t) for t in series.times],
            series.values,
            color=colour.get("fixedColor") or _PALETTE[k % len(_PALETTE)],
            lw=1.3,
            dashes=line.get("dash", ()) if line.get("fill") == "dash" else (),
            label=name,
        )
    _time_axis(ax, *window)
    finite = [v for _, s in lines for v in s.values if math.isfinite(v)]
    if finite and max(finite) == min(finite):
        middle = finite[0]
        ax.set_ylim(middle - 1 if middle == 0 else middle * 0.5, middle + 1 if middle == 0 else middle * 1.5)
    elif finite and min(finite) >= 0:
        ax.set_ylim(0, 1.08 * max(finite))  # headroom over the highest line, as Grafana leaves
    if lines:
        ax.legend(
            loc="upper left",
            bbox_to_anchor=(box.left + 4 / fig.bbox.width, box.bottom + (8 + 16 * rows) / fig.bbox.height),
            bbox_transform=fig.transFigure,
            ncol=columns,
            frameon=False,
            fontsize=8,
            labelcolor=_TEXT,
            handlelength=1.2,
            columnspacing=1.6,
            borderaxespad=0,
        )


def _buckets(target: TargetData) -> tuple[list[str], np.ndarray, np.ndarray]:
    """A heatmap's rows from cumulative `le` series, as Grafana's "heatmap" format makes them:
    the bucket bounds (upper, in order), the times (n,) and the counts per bucket (nbucket, n)."""
    ordered = sorted(target.series, key=lambda s: float(s.labels.get("le", "inf")))
    if not ordered:
        return [], np.zeros(0), np.zeros((0, 0))
    times = ordered[0].times
    cumulative = np.vstack([np.interp(times, s.times, s.values) for s in ordered])
    counts = np.diff(cumulative, axis=0, prepend=0.0)
    return [s.labels.get("le", "") for s in ordered], times, np.clip(counts, 0.0, None)


def _draw_heatmap(fig: Any, box: _Box, data: PanelData, window: tuple[float, float]) -> None:
    from matplotlib.colors import LinearSegmentedColormap
    from matplotlib.ticker import MaxNLocator

    unit = _unit(data.panel)
    bounds, times, counts = _buckets(data.targets[0])
    ax = fig.add_axes(box.inset(0.052, 44 / fig.bbox.height, 0.008, 36 / fig.bbox.height))
    _style_axes(ax, unit)
    ax.grid(False)
    colours = LinearSegmentedColormap.from_list(
        "grafana-oranges", ["#3d1f0a", "#a34a0c", "#f28a1b", "#fdd49e"]
    )
    step = float(times[1] - times[0]) if len(times) > 1 else 1.0
    edges = [_date(t - step / 2) for t in times] + [_date(times[-1] + step / 2)]
    shown = np.ma.masked_less_equal(counts, 1e-9)  # Grafana hides empty cells
    mesh = ax.pcolormesh(edges, np.arange(len(bounds) + 1), shown, cmap=colours, shading="flat")
    # Each row is one bucket, its bounds on its edges (Grafana's "le" layout).
    labels = ["0", *(("+Inf" if b in ("+Inf", "inf") else format_value(float(b), unit)) for b in bounds)]
    ax.set_yticks(np.arange(len(bounds) + 1), labels)
    _time_axis(ax, *window)
    scale = fig.add_axes(
        box.inset(0.052, 16 / fig.bbox.height, box.width - 0.052 - 0.16, box.height - 24 / fig.bbox.height)
    )
    bar = fig.colorbar(mesh, cax=scale, orientation="horizontal")
    bar.outline.set_visible(False)
    bar.ax.tick_params(colors=_WEAK, labelsize=7, length=0)
    bar.ax.xaxis.set_major_locator(MaxNLocator(3))


def _draw_stat(fig: Any, box: _Box, data: PanelData, window: tuple[float, float]) -> None:
    unit = _unit(data.panel)
    series = [s for t in data.targets for s in t.series]
    values = [v for v in series[0].values if math.isfinite(v)]
    last = values[-1] if values else float("nan")
    ax = fig.add_axes(box.inset(0.004, 4 / fig.bbox.height, 0.004, 36 / fig.bbox.height))
    ax.set_facecolor(_PANEL)
    ax.axis("off")
    ax.fill_between(
        [_date(t) for t in series[0].times], series[0].values, color=_STAT_GREEN, alpha=0.15, lw=0
    )
    ax.plot([_date(t) for t in series[0].times], series[0].values, color=_STAT_GREEN, lw=1, alpha=0.6)
    top = max((abs(v) for v in values), default=1.0) or 1.0
    ax.set_ylim(0, 2.5 * top)  # the sparkline in the panel's lower part, under the number
    ax.text(
        0.5,
        0.55,
        format_value(last, unit),
        transform=ax.transAxes,
        ha="center",
        va="center",
        fontsize=30,
        color=_STAT_GREEN,
        weight="bold",
    )


_DRAWERS: dict[str, Callable[[Any, _Box, PanelData, tuple[float, float]], None]] = {
    "timeseries": _draw_timeseries,
    "graph": _draw_timeseries,
    "heatmap": _draw_heatmap,
    "stat": _draw_stat,
}


def _header(fig: Any, *, title: str, window: tuple[float, float]) -> None:
    width, height = fig.bbox.width, fig.bbox.height
    top = 1 - (_PAD + 18) / height
    fig.text(_PAD / width, top, f"Dashboards  ›  {title}", color=_TEXT, fontsize=13, va="center")
    shown = (
        f"{time.strftime('%Y-%m-%d %H:%M:%S', time.gmtime(window[0]))} to "
        f"{time.strftime('%H:%M:%S', time.gmtime(window[1]))} UTC   ·   drawn from Prometheus by "
        "scripts/dashboard_preview.py (not a Grafana screenshot)"
    )
    fig.text(1 - _PAD / width, top, shown, color=_WEAK, fontsize=9, ha="right", va="center")


def _frame(fig: Any, box: _Box, title: str) -> None:
    """A panel's background, border and title."""
    from matplotlib.patches import FancyBboxPatch

    fig.patches.append(
        FancyBboxPatch(
            (box.left, box.bottom),
            box.width,
            box.height,
            boxstyle="round,pad=0,rounding_size=0.002",
            transform=fig.transFigure,
            facecolor=_PANEL,
            edgecolor=_BORDER,
            linewidth=1,
            zorder=-1,  # under the panel's axes
        )
    )
    top = box.bottom + box.height - 18 / fig.bbox.height
    fig.text(box.left + 8 / fig.bbox.width, top, title, color=_TEXT, fontsize=10.5, va="center")


def _note(fig: Any, box: _Box, text: str) -> None:
    middle = (box.left + box.width / 2, box.bottom + box.height / 2)
    fig.text(*middle, text, color=_WEAK, fontsize=13, ha="center", va="center")


def draw(panels: Sequence[PanelData], *, title: str, window: tuple[float, float], out: Path) -> None:
    """The dashboard as Grafana lays it out, into the PNG `out`."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    width, height, boxes = _layout(panels)
    fig = plt.figure(figsize=(width / _DPI, height / _DPI), dpi=_DPI, facecolor=_CANVAS)
    _header(fig, title=title, window=window)
    for data, box in zip(panels, boxes, strict=True):
        _frame(fig, box, data.title)
        kind = str(data.panel.get("type"))
        if not any(t.series for t in data.targets):
            _note(fig, box, "No data")
        elif kind in _DRAWERS:
            _DRAWERS[kind](fig, box, data, window)
        else:
            _note(fig, box, f"(a {kind} panel: not drawn)")
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=_DPI, facecolor=_CANVAS)
    plt.close(fig)


# ---------------------------------------------------------------------------------------------
# The command


def _interrupt(signum: int, frame: FrameType | None) -> None:
    raise KeyboardInterrupt  # SIGTERM stops us as Ctrl-C does: every `with` closes what it started


def _report(panels: Sequence[PanelData]) -> list[str]:
    """Print each panel's series; the titles of those that have none (Grafana: "No data")."""
    empty = []
    for data in panels:
        counts = ", ".join(f"{t.ref_id} {len(t.series)}" for t in data.targets)
        print(f"  {data.title}: series {counts}")
        for target in data.empty_targets():
            print(f"    no data: {target.expr}")
        if data.empty_targets():
            empty.append(data.title)
    return empty


def _first_open(prometheus: Prometheus, *, start: float, timeout: float) -> float | None:
    """When the server first had a session open (Unix seconds, as scraped), waiting up to `timeout`
    seconds for it; None if it had none."""
    deadline = time.monotonic() + timeout
    while True:
        now = time.time()
        found = prometheus.query_range(
            "sum(jitdyn_open_sessions) > 0", start=start, end=now, step=SCRAPE_INTERVAL
        )
        if found or time.monotonic() > deadline:
            return float(found[0].times[0]) if found else None
        time.sleep(1.0)


def run(args: argparse.Namespace) -> int:
    dashboard = json.loads(args.dashboard.read_text())
    with contextlib.ExitStack() as stack:
        workdir = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="jitdyn-dashboard-")))
        server = stack.enter_context(JitdynServer(workdir, processes=args.processes))
        print(f"jitdyn serve on {server.address}, metrics on {server.metrics_address}")
        prometheus = stack.enter_context(Prometheus(workdir, targets=[server.metrics_address]))
        print(f"prometheus on {prometheus.url}, scraping every {SCRAPE_INTERVAL:g} s")
        start = time.time()
        load = stack.enter_context(
            Load(server.address, workdir, runs=LOAD, seconds=args.seconds, wait=args.wait)
        )
        print(
            f"{len(LOAD)} demo sessions of {args.seconds:g} s, each admitted within {args.wait:g} s or not run: "
            + ", ".join(f"{r.model} {r.scenario}" for r in LOAD)
        )
        opened = _first_open(prometheus, start=start, timeout=args.wait)
        if opened is not None:
            print(f"first session open {opened - start:.0f} s after the start")
            time.sleep(min(10.0, args.seconds / 4))
        print(f"refused, as it should be: {refuse_one(server.address)}")
        failures = load.wait(timeout=args.wait + args.seconds + 120)
        print(f"{len(LOAD) - len(failures)} of {len(LOAD)} demo sessions ran")
        for failure in failures:
            print(f"  did not run: {failure}")
        time.sleep(3 * SCRAPE_INTERVAL)  # the last ticks' scrape
        end = time.time()
        # From a little before the first session opened: a wait for admission is not the picture.
        shown = start if opened is None else max(start, opened - 15.0)
        step = max(SCRAPE_INTERVAL, (end - shown) / 300)
        panels = evaluate(
            dashboard,
            lambda expr: prometheus.query_range(expr, start=shown, end=end, step=step),
            step=step,
            span=end - shown,
        )
    empty = _report(panels)
    draw(panels, title=str(dashboard.get("title", "")), window=(shown, end), out=args.out)
    print(f"wrote {args.out}")
    if empty:
        print(f"panels with no data: {', '.join(empty)}")
        return 1
    print("every panel has data")
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description="Draw deploy/grafana/jitdyn.json from a real server under demo load, scraped by a real "
        "Prometheus (needs the prometheus binary; Grafana is not needed).",
    )
    parser.add_argument(
        "--out", type=Path, default=OUT, help=f"the PNG to write (default {OUT.relative_to(ROOT)})"
    )
    parser.add_argument("--dashboard", type=Path, default=DASHBOARD, help="the Grafana dashboard JSON")
    parser.add_argument(
        "--seconds", type=float, default=60.0, help="length of the demo sessions, s (default 60)"
    )
    parser.add_argument(
        "--wait",
        type=float,
        default=300.0,
        help="how long a demo session waits to be admitted, s (default 300)",
    )
    parser.add_argument("--processes", type=int, default=2, help="server processes (default 2)")
    parser.add_argument("--demo-worker", metavar="JSON", help=argparse.SUPPRESS)  # one of Load's processes
    args = parser.parse_args(argv)
    if args.demo_worker:
        job = json.loads(args.demo_worker)
        return demo_worker(
            job["address"], DemoRun(**job["run"]), seconds=job["seconds"], wait=job["wait"], seed=job["seed"]
        )
    for name in ("seconds", "wait"):
        if getattr(args, name) <= 0:
            parser.error(f"--{name} must be > 0, got {getattr(args, name):g}")
    signal.signal(signal.SIGTERM, _interrupt)
    try:
        return run(args)
    except KeyboardInterrupt:
        print("interrupted: everything it started is stopped", file=sys.stderr)
        return 130
    except (PreviewError, JitdynError, OSError, json.JSONDecodeError) as exc:
        print(f"dashboard_preview: {exc}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
