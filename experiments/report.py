"""The report of an experiment run: tables (markdown and CSV) and plots (PNG, matplotlib Agg).

Each experiment returns a `Section`; `write_report` puts every section into report.md, every
table into <name>.csv, beside the PNGs the sections drew.
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Generic, TypeVar

import numpy as np

from jitdyn.experiments.runner import Trace

if TYPE_CHECKING:
    import matplotlib.figure

__all__ = [
    "Column",
    "Figure",
    "Section",
    "Table",
    "fmt",
    "plot_bars",
    "plot_error_over_time",
    "plot_estimates",
    "plot_gap_errors",
    "write_report",
]

# Small PNGs: the docs commit them.
_DPI = 144

_Item = TypeVar("_Item")
_Label = TypeVar("_Label", bound=str)  # a run's name in a plot's legend
_Item_contra = TypeVar("_Item_contra", contravariant=True)


@dataclass(frozen=True)
class Column(Generic[_Item_contra]):
    """One column of a table: its header, and how a row's item gives its cell."""

    header: str
    cell: Callable[[_Item_contra], object]


@dataclass(frozen=True)
class Table:
    """A table of the report; `name` is its CSV file's stem."""

    name: str
    title: str
    columns: tuple[str, ...]
    rows: tuple[tuple[object, ...], ...]

    def __post_init__(self) -> None:
        for row in self.rows:
            if len(row) != len(self.columns):
                raise ValueError(
                    f"table {self.name}: every row must have {len(self.columns)} cells, got {len(row)}"
                )

    @classmethod
    def of(cls, name: str, title: str, columns: Sequence[Column[_Item]], items: Iterable[_Item]) -> Table:
        """The table whose header and rows both come from `columns`: a row per item."""
        rows = tuple(tuple(column.cell(item) for column in columns) for item in items)
        return cls(name, title, tuple(column.header for column in columns), rows)

    def write_csv(self, path: Path) -> None:
        with path.open("w", newline="", encoding="utf-8") as f:
            writer = csv.writer(f)
            writer.writerow(self.columns)
            for row in self.rows:
                writer.writerow([_raw(c) for c in row])

    def markdown(self) -> str:
        lines = [
            "| " + " | ".join(self.columns) + " |",
            "|" + "---|" * len(self.columns),
        ]
        for row in self.rows:
            lines.append("| " + " | ".join(fmt(c) for c in row) + " |")
        return "\n".join(lines)

    def numbers(self) -> list[float]:
        """Every numeric cell, for checks that a report is finite."""
        return [
            float(c)
            for row in self.rows
            for c in row
            if isinstance(c, (int, float)) and not isinstance(c, bool)
        ]


@dataclass(frozen=True)
class Figure:
    file: str  # relative to the report
    caption: str


@dataclass(frozen=True)
class Section:
    name: str
    title: str
    text: str
    tables: tuple[Table, ...] = ()
    figures: tuple[Figure, ...] = ()
    notes: tuple[str, ...] = field(default_factory=tuple)


def _raw(cell: object) -> object:
    if isinstance(cell, float):
        # float() first: numpy's scalars are floats whose repr is "np.float64(...)".
        return repr(float(cell))
    if isinstance(cell, tuple):
        return ";".join(str(_raw(c)) for c in cell)
    return "" if cell is None else cell


def fmt(cell: object) -> str:
    """A cell for humans: 4 significant digits, intervals in brackets, '-' for nothing."""
    if cell is None:
        return "-"
    if isinstance(cell, bool):
        return "yes" if cell else "no"
    if isinstance(cell, int):
        return str(cell)
    if isinstance(cell, float):
        if math.isnan(cell):
            return "n/a"
        if math.isinf(cell):
            return "inf" if cell > 0 else "-inf"
        if cell != 0 and (abs(cell) < 1e-2 or abs(cell) >= 1e5):
            return f"{cell:.4e}"
        return f"{cell:.4g}"
    if isinstance(cell, tuple):
        return "[" + "; ".join(fmt(c) for c in cell) + "]"
    return str(cell).replace("|", "\\|")


def write_report(out: Path, sections: Sequence[Section], *, header: str) -> Path:
    """Writes report.md and one CSV per table into `out`; returns the report's path."""
    out.mkdir(parents=True, exist_ok=True)
    parts = [header.rstrip(), ""]
    for section in sections:
        parts += [f"## {section.title}", "", section.text.strip(), ""]
        for table in section.tables:
            table.write_csv(out / f"{table.name}.csv")
            parts += [f"**{table.title}** ([{table.name}.csv]({table.name}.csv))", "", table.markdown(), ""]
        for figure in section.figures:
            parts += [f"![{figure.caption}]({figure.file})", "", f"*{figure.caption}*", ""]
        for note in section.notes:
            parts += [f"> {note}", ""]
    path = out / "report.md"
    path.write_text("\n".join(parts), encoding="utf-8")
    return path


def _pyplot() -> Any:
    """matplotlib's pyplot on the Agg backend (no display: CI and servers). Imported when a plot is
    drawn, not with this module, so that `jitdyn experiments --help` works without the extra."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _finish(fig: matplotlib.figure.Figure, path: Path) -> None:
    from PIL import Image

    fig.tight_layout()
    buffer = io.BytesIO()
    fig.savefig(buffer, dpi=_DPI, format="png")
    _pyplot().close(fig)
    # A 256-colour palette keeps line plots sharp at a third of the size: the docs commit them.
    with Image.open(buffer) as image:
        image.convert("RGB").quantize(colors=256).save(path, format="PNG", optimize=True)


def _unit(trace: Trace, dof: int, block: str) -> str:
    """The unit of `block` (q, qd, qdd) of one dof: rad, rad/s, rad/s² on a rotation, m... on a
    translation; "rad or m" when the trace does not say."""
    unit = trace.dof_units[dof] if dof < len(trace.dof_units) else "rad or m"
    return unit + {"q": "", "qd": "/s", "qdd": "/s²"}[block] if "or" not in unit else unit


def plot_estimates(
    traces: Mapping[_Label, Trace], path: Path, *, title: str, joints: Sequence[int] | None = None
) -> None:
    """Estimate against truth as the thesis' figures 4.2-4.14: one panel per joint and component.

    `traces` maps a legend label to a run of the same object; a truth shared by the runs is drawn
    once, in black.
    """
    first = next(iter(traces.values()))
    blocks = ("q", "qd", "qdd")[: first.nx // first.nv]
    rows = list(joints) if joints is not None else list(range(first.nv))
    fig, axes = _pyplot().subplots(
        len(rows), len(blocks), figsize=(3.6 * len(blocks), 2.0 * len(rows) + 0.7), squeeze=False
    )
    styles = ("--", ":", "-.")
    # With the control fed from the estimate (CONTROLLED), every run moves its own way: each run's
    # estimate is drawn against its own truth.
    shared_truth = all(
        t.truth_state.shape == first.truth_state.shape and np.allclose(t.truth_state, first.truth_state)
        for t in traces.values()
    )
    for r, joint in enumerate(rows):
        for c, block in enumerate(blocks):
            ax = axes[r][c]
            if shared_truth:
                truth, _ = first.component(block)
                ax.plot(first.t, truth[:, joint], color="black", lw=1.2, label="truth")
            for i, (label, trace) in enumerate(traces.items()):
                truth, estimate = trace.component(block)
                color = f"C{i}"
                if not shared_truth:
                    ax.plot(
                        trace.t,
                        truth[:, joint],
                        "-",
                        color=color,
                        lw=1.2,
                        alpha=0.5,
                        label=f"truth ({label} run)",
                    )
                ax.plot(
                    trace.t, estimate[:, joint], styles[i % len(styles)], color=color, lw=1.0, label=label
                )
            name = first.joint_names[joint] if joint < len(first.joint_names) else str(joint)
            ax.set_title(f"{name}: {block}", fontsize=9)
            ax.set_ylabel(f"{block} ({_unit(first, joint, block)})", fontsize=8)
            ax.tick_params(labelsize=8)
            if r == len(rows) - 1:
                ax.set_xlabel("t (s)", fontsize=8)
    axes[0][0].legend(fontsize=6, loc="best")
    fig.suptitle(title, fontsize=9)
    _finish(fig, path)


def plot_error_over_time(traces: Mapping[_Label, Trace], path: Path, *, title: str, joint: int) -> None:
    """|q error| of one joint over time, log scale (the thesis' figure 4.15 for myoHand's 23rd joint)."""
    fig, ax = _pyplot().subplots(figsize=(7, 3.6))
    for label, trace in traces.items():
        truth, estimate = trace.component("q")
        err = np.abs(truth[:, joint] - estimate[:, joint])
        ax.semilogy(trace.t, np.maximum(err, 1e-12), lw=1.0, label=label)
    first = next(iter(traces.values()))
    ax.set_xlabel("t (s)")
    ax.set_ylabel(f"|q error| of {first.joint_names[joint]} ({_unit(first, joint, 'q')})")
    ax.set_title(title, fontsize=9)
    ax.legend(fontsize=7)
    _finish(fig, path)


def plot_gap_errors(
    profiles: Mapping[str, Mapping[int, float]],
    path: Path,
    *,
    dt: float,
    title: str,
    marks: Sequence[float] = (),
) -> None:
    """RMS q error against the time since the last frame, one line per estimator (log scale)."""
    fig, ax = _pyplot().subplots(figsize=(7, 4))
    for label, profile in profiles.items():
        hs = sorted(profile)
        ax.semilogy(
            [h * dt * 1000 for h in hs], [max(profile[h], 1e-12) for h in hs], marker=".", lw=1.0, label=label
        )
    for m in marks:
        ax.axvline(m * 1000, color="grey", lw=0.6, ls=":")
    ax.set_xlabel("time without frames (ms)")
    ax.set_ylabel("RMS q error (rad or m)")
    ax.set_title(title, fontsize=9)
    ax.legend(fontsize=7)
    _finish(fig, path)


def plot_bars(
    groups: Sequence[str],
    series: Mapping[str, Sequence[float]],
    path: Path,
    *,
    title: str,
    ylabel: str,
    hline: float | None = None,
    hline_label: str = "",
    log: bool = False,
) -> None:
    """Grouped bars: one group per model, one bar per series (e.g. per worker count)."""
    fig, ax = _pyplot().subplots(figsize=(max(6, 1.3 * len(groups) + 2.5), 4))
    width = 0.8 / max(1, len(series))
    x = np.arange(len(groups))
    for i, (label, values) in enumerate(series.items()):
        ax.bar(x + (i - (len(series) - 1) / 2) * width, values, width, label=label)
    if hline is not None:
        ax.axhline(hline, color="red", lw=0.8, ls="--", label=hline_label)
    ax.set_xticks(x, groups, fontsize=7, rotation=20)
    ax.set_ylabel(ylabel)
    if log:
        ax.set_yscale("log")
    ax.set_title(title, fontsize=9)
    ax.legend(fontsize=7)
    _finish(fig, path)
