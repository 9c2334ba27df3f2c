"""experiments.report: the figures are big enough to read and every axis says its unit."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

pytest.importorskip("matplotlib")

from PIL import Image

from jitdyn.client import Client
from jitdyn.experiments import report
from jitdyn.experiments.runner import RunSpec, run_lockstep
from jitdyn.vocabulary import Scenario


@pytest.fixture(scope="module")
def biped_trace(server: Any) -> Any:
    """0.2 s of the biped (slides and hinges) rocking, LOCKSTEP on a real server."""
    with Client(server.address, timeout=60) as client:
        return run_lockstep(client, RunSpec("biped", Scenario.EXTERNAL, seconds=0.2), progress=False)


def test_estimate_plots_are_large_and_label_each_axis_with_its_unit(
    biped_trace: Any, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    labels: list[tuple[str, str, str]] = []
    finish = report._finish

    def record(fig: Any, path: Path) -> None:
        labels.extend((ax.get_title(), ax.get_ylabel(), ax.get_xlabel()) for ax in fig.axes)
        finish(fig, path)

    monkeypatch.setattr(report, "_finish", record)
    path = tmp_path / "biped.png"
    report.plot_estimates({"JITDYN": biped_trace}, path, title="biped", joints=[1, 2])
    with Image.open(path) as image:
        assert image.width >= 1000 and image.height >= 600, image.size
    by_title = {title: (y, x) for title, y, x in labels}
    # root_z is a slide (m), left_hip a hinge (rad).
    assert by_title["root_z: q"][0] == "q (m)" and by_title["root_z: qd"][0] == "qd (m/s)"
    assert by_title["left_hip: q"][0] == "q (rad)" and by_title["left_hip: qd"][0] == "qd (rad/s)"
    assert by_title["left_hip: q"][1] == "t (s)"


def test_the_error_plot_is_large(biped_trace: Any, tmp_path: Path) -> None:
    path = tmp_path / "error.png"
    report.plot_error_over_time({"JITDYN": biped_trace}, path, title="biped", joint=0)
    with Image.open(path) as image:
        assert image.width >= 900 and image.height >= 450, image.size


def test_an_acceleration_is_in_units_per_second_squared(biped_trace: Any) -> None:
    assert report._unit(biped_trace, 1, "qdd") == "m/s²" and report._unit(biped_trace, 2, "qdd") == "rad/s²"
