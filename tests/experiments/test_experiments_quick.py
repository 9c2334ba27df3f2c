"""`jitdyn experiments --quick` end to end against an in-process server: every report file is there
and every number in it is finite. The whole run (about a minute) is marked slow, to keep CI's run
short; CI runs the thesis' two tables the same way (`pytest -m slow tests/experiments` runs all)."""

from __future__ import annotations

import csv
import math
import re
import subprocess
from pathlib import Path

import pytest

from jitdyn.experiments import EXPERIMENTS, main


def _cells(path: Path) -> list[str]:
    with path.open(encoding="utf-8") as f:
        rows = list(csv.reader(f))
    assert len(rows) >= 2, f"{path.name} has no rows"
    return [cell for row in rows[1:] for cell in row]


def _numbers(cells: list[str]) -> list[float]:
    out = []
    for cell in cells:
        for part in cell.split(";"):
            try:
                out.append(float(part))
            except ValueError:
                continue
    return out


def _finite(path: Path) -> None:
    assert not [c for c in _cells(path) if "np." in c], f"{path.name} holds numpy reprs, not numbers"
    numbers = _numbers(_cells(path))
    assert numbers, f"{path.name} holds no numbers"
    bad = [x for x in numbers if not math.isfinite(x)]
    assert not bad, f"{path.name} holds non-finite numbers {bad[:5]}"


def test_the_thesis_tables_run_quick_with_finite_numbers(tmp_path: Path) -> None:
    out = tmp_path / "out"
    assert main(["table_4_4", "table_4_6", "--quick", "--no-progress", "--out", str(out)]) == 0
    assert {p.stem for p in out.glob("*.csv")} == {"table_4_4", "table_4_6"}
    for path in out.glob("*.csv"):
        _finite(path)
    assert len(list(out.glob("*.png"))) >= 2


@pytest.mark.slow
@pytest.mark.timeout(240)
def test_quick_run_writes_every_table_and_plot_with_finite_numbers(tmp_path: Path) -> None:
    out = tmp_path / "out"
    assert main(["--quick", "--no-progress", "--out", str(out)]) == 0
    report = (out / "report.md").read_text(encoding="utf-8")
    head = subprocess.run(
        ["git", "rev-parse", "--short", "HEAD"],
        cwd=Path(__file__).parent,
        capture_output=True,
        text=True,
        check=False,
    ).stdout.strip()
    if head:  # a git checkout: the run names the commit it started on
        assert re.search(rf"- run: started \d{{4}}-\d\d-\d\d \d\d:\d\d UTC, commit {head}\b", report), report[
            :400
        ]
    for experiment in EXPERIMENTS.values():
        assert experiment.name in report or experiment.title in report
    csvs = sorted(out.glob("*.csv"))
    pngs = sorted(out.glob("*.png"))
    assert {p.stem for p in csvs} >= {
        "table_4_2",
        "table_4_4",
        "table_4_6",
        "table_4_8",
        "table_4_8_nees",
        "table_4_9",
        "table_4_9_nees",
        "table_4_10",
        "myohand",
        "fig_4_16",
        "fig_4_17",
        "gaps",
        "prior",
        "network",
    }
    assert len(pngs) >= 12
    for path in csvs:
        _finite(path)
    for path in pngs:
        assert path.stat().st_size > 1000


def test_help_names_every_experiment(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exit_info:
        main(["--help"])
    assert exit_info.value.code == 0
    text = capsys.readouterr().out
    for name in EXPERIMENTS:
        assert name in text


def test_unknown_experiment_is_refused_by_name(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exit_info:
        main(["table_9_9"])
    assert exit_info.value.code == 2
    assert "unknown experiment(s) ['table_9_9']" in capsys.readouterr().err
