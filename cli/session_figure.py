"""One stored session drawn as one matplotlib figure, every panel on the same time axis: a strip of
each tick's source, then per joint its measured and answered q beside its answered generalized
force, then the network's and the server's lateness, then the filter's NIS.

    figure = draw_session(timeline, joints, title=["session ...", "ticks ..."], dt=0.01, realtime=True)

Gaps (ticks no frame was ever used for) are shaded in every panel. Lines are decimated to about
MAX_DRAWN points; the source strip and the shaded gaps are computed from every tick, so that no
prediction, correction or rejection is lost to the decimation.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Final

import numpy as np
import numpy.typing as npt
from matplotlib.axes import Axes
from matplotlib.colors import to_rgb
from matplotlib.figure import Figure

from jitdyn.storage.joints import Joint
from jitdyn.storage.records import FORCE_UNITS
from jitdyn.storage.timeline import Timeline
from jitdyn.vocabulary import Source

__all__ = ["MAX_DRAWN", "Decimation", "decimation", "draw_session"]

# Ticks drawn per line (about a point per pixel of the figure's width) and markers per kind.
MAX_DRAWN: Final = 3000
# Columns of the source strip and the resolution gaps are merged at.
_BINS: Final = 1500

_MEASURED_LINE: Final = "#222222"
_ANSWERED_LINE: Final = "tab:blue"
_COLORS: Final = {
    Source.MEASURED: "tab:blue",
    Source.PREDICTED: "tab:orange",
    Source.CORRECTED: "tab:green",
}
_REJECTED: Final = "tab:red"
_GAP: Final = "#bbbbbb"
_LABELS: Final = {
    Source.PREDICTED: "PREDICTED (no frame yet)",
    Source.CORRECTED: "CORRECTED (late frame replayed)",
}


@dataclass(frozen=True)
class Decimation:
    """How many ticks a session has and every how many of them a line draws."""

    ticks: int
    stride: int

    @property
    def note(self) -> str:
        """What the title says about it; "" when every tick is drawn."""
        if self.stride == 1:
            return ""
        return (
            f"every {_ordinal(self.stride)} tick drawn of {self.ticks:,}".replace(",", " ")
            + " (sources and gaps: every tick)"
        )


def _ordinal(k: int) -> str:
    suffix = "th" if 10 <= k % 100 <= 20 else {1: "st", 2: "nd", 3: "rd"}.get(k % 10, "th")
    return f"{k}{suffix}"


def decimation(ticks: int, *, limit: int = MAX_DRAWN) -> Decimation:
    return Decimation(ticks=ticks, stride=max(1, math.ceil(ticks / limit)))


def _thin(index: npt.NDArray[np.intp], limit: int = MAX_DRAWN) -> npt.NDArray[np.intp]:
    return index[:: max(1, math.ceil(len(index) / limit))]


def _gap_spans(timeline: Timeline, dt: float) -> list[tuple[float, float]]:
    """(start, width) of each run of gap ticks, runs closer than a strip column merged."""
    gap = timeline.gap
    if not gap.any():
        return []
    edges = np.diff(np.concatenate([[0], gap.astype(np.int8), [0]]))
    starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1) - 1
    t = timeline.t
    span = float(t[-1] - t[0]) + dt
    merged: list[list[float]] = []
    for a, b in zip(t[starts] - dt / 2, t[ends] + dt / 2, strict=True):
        if merged and a - merged[-1][1] < span / _BINS:
            merged[-1][1] = float(b)
        else:
            merged.append([float(a), float(b)])
    return [(a, b - a) for a, b in merged]


def _shade(ax: Axes, spans: list[tuple[float, float]]) -> None:
    if spans:
        ax.broken_barh(spans, (0, 1), transform=ax.get_xaxis_transform(), color=_GAP, alpha=0.45, lw=0)


def _source_strip(ax: Axes, timeline: Timeline, dt: float) -> None:
    """One row per kind of answer, a column per time bin, coloured where any tick of the bin had it."""
    measured = timeline.t[timeline.source == Source.MEASURED.value]
    predicted = timeline.t[timeline.source == Source.PREDICTED.value]
    corrected = timeline.t[timeline.corrected]
    rejected = timeline.rejections.t
    # (label, times, colour) of each row, top to bottom.
    rows = (
        (f"MEASURED {len(measured)}", measured, _COLORS[Source.MEASURED]),
        (f"PREDICTED {len(predicted)}", predicted, _COLORS[Source.PREDICTED]),
        (f"CORRECTED (late) {len(corrected)}", corrected, _COLORS[Source.CORRECTED]),
        (f"rejected frames {len(rejected)}", rejected, _REJECTED),
    )
    lo, hi = float(timeline.t[0]) - dt / 2, float(timeline.t[-1]) + dt / 2
    bins = max(1, min(_BINS, len(timeline.t)))
    image = np.ones((len(rows), bins, 3))
    for i, (_, times, color) in enumerate(rows):
        counts, _ = np.histogram(times, bins=bins, range=(lo, hi))
        image[i, counts > 0] = np.array(to_rgb(color))
    ax.imshow(image, aspect="auto", interpolation="nearest", extent=(lo, hi, len(rows) - 0.5, -0.5))
    ax.set_yticks(range(len(rows)), [label for label, _, _ in rows], fontsize=8)
    ax.tick_params(axis="y", length=0)
    ax.set_title("source of each tick's answer", fontsize=9, loc="left")


@dataclass(frozen=True)
class _Picks:
    """Indices of the ticks each layer draws: lines every `stride`, markers thinned per kind."""

    line: npt.NDArray[np.intp]
    predicted: npt.NDArray[np.intp]
    corrected: npt.NDArray[np.intp]
    rejected_late: npt.NDArray[np.intp]


def _picks(timeline: Timeline, stride: int) -> _Picks:
    late_frames = np.flatnonzero(~np.isnan(timeline.rejections.frame_qpos).all(axis=1))
    return _Picks(
        line=np.arange(0, len(timeline.t), stride),
        predicted=_thin(np.flatnonzero(timeline.source == Source.PREDICTED.value)),
        corrected=_thin(np.flatnonzero(timeline.corrected)),
        rejected_late=_thin(late_frames),
    )


def _joint_q(ax: Axes, timeline: Timeline, joint: Joint, picks: _Picks) -> None:
    t, rejected = timeline.t, timeline.rejections
    for k, (column, name) in enumerate(zip(joint.qpos, joint.qpos_names, strict=True)):
        first = k == 0
        ax.plot(
            t[picks.line],
            timeline.frame_qpos[picks.line, column],
            color=_MEASURED_LINE,
            lw=1.6,
            alpha=0.55,
            label="measured (frame)" if first else None,
        )
        ax.plot(
            t[picks.line],
            timeline.answered_qpos[picks.line, column],
            color=_ANSWERED_LINE,
            lw=0.9,
            label="answered when due" if first else None,
        )
        _markers(
            ax,
            t,
            timeline.answered_qpos[:, column],
            at=picks.predicted,
            kind=Source.PREDICTED,
            labelled=first,
        )
        _markers(
            ax,
            t,
            timeline.corrected_qpos[:, column],
            at=picks.corrected,
            kind=Source.CORRECTED,
            labelled=first,
        )
        if picks.rejected_late.size:
            ax.scatter(
                rejected.t[picks.rejected_late],
                rejected.frame_qpos[picks.rejected_late, column],
                marker="x",
                s=14,
                lw=0.8,
                color=_REJECTED,
                label="late frame, rejected" if first else None,
                zorder=3,
            )
        if len(joint.qpos) > 1:
            ax.annotate(name, (t[-1], timeline.answered_qpos[-1, column]), fontsize=6, color="#555555")
    columns = list(joint.qpos)
    _fit(
        ax,
        timeline.frame_qpos[:, columns],
        timeline.answered_qpos[:, columns],
        timeline.corrected_qpos[:, columns],
        rejected.frame_qpos[:, columns],
    )
    unit = joint.dof_units[0] if len(joint.qpos) == 1 and joint.dof_units else ""
    ax.set_ylabel(f"{joint.name}\nq{f' ({unit})' if unit else ''}", fontsize=8)


def _fit(ax: Axes, *arrays: npt.NDArray[np.float64]) -> None:
    """Limit the y axis to where nearly all values lie when a few outliers (a start-up transient, a
    diverging prediction) would flatten the rest, and say in the panel how many are off scale."""
    values = np.concatenate([a.ravel() for a in arrays])
    values = values[np.isfinite(values)]
    if values.size < 20:
        return
    lo, hi = np.percentile(values, [0.5, 99.5])
    full = float(values.max() - values.min())
    if full <= 3 * max(float(hi - lo), 1e-12):
        return
    margin = 0.15 * max(float(hi - lo), 1e-9)
    lo, hi = lo - margin, hi + margin
    ax.set_ylim(lo, hi)
    off = int(((values < lo) | (values > hi)).sum())
    ax.text(
        0.995,
        0.96,
        f"{off} values off scale",
        transform=ax.transAxes,
        ha="right",
        va="top",
        fontsize=7,
        color="#555555",
    )


def _markers(
    ax: Axes,
    t: npt.NDArray[np.float64],
    values: npt.NDArray[np.float64],
    *,
    at: npt.NDArray[np.intp],
    kind: Source,
    labelled: bool,
) -> None:
    """A dot at each tick of `at`, coloured by `kind`; in the legend once (`labelled`)."""
    if at.size:
        ax.scatter(
            t[at],
            values[at],
            s=9,
            color=_COLORS[kind],
            label=_LABELS[kind] if labelled else None,
            zorder=3,
            lw=0,
        )


def _joint_force(ax: Axes, timeline: Timeline, joint: Joint, picks: _Picks) -> None:
    t = timeline.t
    drawn = False
    for dof in joint.dofs:
        if dof >= timeline.answered_qfrc.shape[1]:
            continue
        drawn = True
        ax.plot(t[picks.line], timeline.answered_qfrc[picks.line, dof], color="tab:purple", lw=0.9)
        _markers(
            ax, t, timeline.answered_qfrc[:, dof], at=picks.predicted, kind=Source.PREDICTED, labelled=False
        )
        _markers(
            ax, t, timeline.corrected_qfrc[:, dof], at=picks.corrected, kind=Source.CORRECTED, labelled=False
        )
    dofs = [dof for dof in joint.dofs if dof < timeline.answered_qfrc.shape[1]]
    _fit(ax, timeline.answered_qfrc[:, dofs], timeline.corrected_qfrc[:, dofs])
    if not drawn:
        ax.text(
            0.5,
            0.5,
            "no inverse dynamics stored",
            transform=ax.transAxes,
            ha="center",
            va="center",
            fontsize=8,
        )
    units = set(joint.dof_units)
    unit = FORCE_UNITS.get(units.pop(), "") if len(units) == 1 else ""
    ax.set_ylabel(f"qfrc_inverse{f' ({unit})' if unit else ''}", fontsize=8)


def _network(ax: Axes, timeline: Timeline, picks: _Picks, *, dt: float, realtime: bool) -> None:
    if not realtime:
        # LOCKSTEP stores 0: each frame is its own tick's deadline.
        ax.text(
            0.5,
            0.5,
            "LOCKSTEP: each frame is answered as it arrives; no network lateness",
            transform=ax.transAxes,
            ha="center",
            va="center",
            fontsize=8,
        )
        ax.set_yticks([])
        ax.set_ylabel("network", fontsize=8)
        return
    delay_ms = timeline.frame_delay * 1e3
    rejected = timeline.rejections
    on_time = picks.line[~timeline.corrected[picks.line]]
    for at, times, values, style in (
        (
            on_time,
            timeline.t,
            delay_ms,
            {"s": 8, "color": _COLORS[Source.MEASURED], "label": "frame on time"},
        ),
        (
            picks.corrected,
            timeline.t,
            delay_ms,
            {"s": 9, "color": _COLORS[Source.CORRECTED], "label": "late frame (CORRECTED)"},
        ),
        (
            picks.rejected_late,
            rejected.t,
            rejected.frame_delay * 1e3,
            {"s": 14, "marker": "x", "color": _REJECTED, "label": "late frame, rejected"},
        ),
    ):
        at = at[np.isfinite(values[at])]  # a rejection may keep its frame but not its arrival
        if at.size:
            ax.scatter(times[at], values[at], lw=0.8 if "marker" in style else 0, **style)  # type: ignore[arg-type]
    ax.axhline(dt * 1e3, color="#777777", lw=0.8, ls="--", label=f"one tick ({dt * 1e3:g} ms)")
    ax.set_ylabel("network\nframe after its\ntick (ms)", fontsize=8)


def _server(ax: Axes, timeline: Timeline, picks: _Picks, dt: float) -> None:
    # Log scale: answers take from a fraction of a millisecond to a tick and more; 0 is not drawn.
    t = timeline.t[picks.line]
    for values, color, label in (
        (timeline.receive_to_send_us, "tab:brown", "arrival (or deadline) to answer sent"),
        (timeline.compute_us, "tab:cyan", "compute"),
    ):
        ms = values[picks.line] / 1e3
        ax.plot(t, np.where(ms > 0, ms, np.nan), color=color, lw=0.8, label=label)
    ax.axhline(dt * 1e3, color="#777777", lw=0.8, ls="--", label=f"one tick ({dt * 1e3:g} ms)")
    ax.set_yscale("log")
    ax.set_ylabel("server\nanswer (ms)", fontsize=8)


def _nis(ax: Axes, timeline: Timeline, picks: _Picks) -> None:
    nis = timeline.nis
    shown = picks.line[np.isfinite(nis[picks.line]) & (nis[picks.line] > 0)]
    if shown.size == 0:
        ax.text(
            0.5,
            0.5,
            "no NIS stored (no filter update used a measurement)",
            transform=ax.transAxes,
            ha="center",
            va="center",
            fontsize=8,
        )
        ax.set_yticks([])
    else:
        ax.scatter(timeline.t[shown], nis[shown], s=4, color="tab:gray", lw=0)
        ax.set_yscale("log")
    ax.set_ylabel("filter\nNIS", fontsize=8)


def _legend(ax: Axes) -> None:
    handles, labels = ax.get_legend_handles_labels()
    if handles:
        ax.legend(handles, labels, fontsize=7, loc="upper left", ncols=len(handles), framealpha=0.8)


def _key(strip: Axes, ax: Axes) -> None:
    """The legend of the joint panels `ax`, once, above the source strip: inside a joint's panel it
    would hide its data."""
    from matplotlib.patches import Patch

    handles, labels = ax.get_legend_handles_labels()
    handles.append(Patch(color=_GAP, alpha=0.45, lw=0))
    labels.append("gap: no frame ever used")
    strip.legend(
        handles,
        labels,
        loc="lower right",
        bbox_to_anchor=(1.0, 1.0),
        ncols=len(handles),
        fontsize=8,
        frameon=False,
    )


def draw_session(
    timeline: Timeline, joints: Sequence[Joint], *, title: Sequence[str], dt: float, realtime: bool
) -> Figure:
    """The figure of a session with at least one tick; `title` its lines, top to bottom."""
    stride = decimation(len(timeline.t)).stride
    picks = _picks(timeline, stride)
    spans = _gap_spans(timeline, dt)
    heights = [0.9, *[1.7] * len(joints), 1.5 if realtime else 0.45, 1.4, 1.3]
    figure = Figure(figsize=(15, sum(heights) + 0.4 * len(title) + 0.6), layout="constrained")
    grid = figure.add_gridspec(len(heights), 2, height_ratios=heights, width_ratios=[1.2, 1.0])
    strip = figure.add_subplot(grid[0, :])
    _source_strip(strip, timeline, dt)
    for row, joint in enumerate(joints, start=1):
        q_ax = figure.add_subplot(grid[row, 0], sharex=strip)
        f_ax = figure.add_subplot(grid[row, 1], sharex=strip)
        _joint_q(q_ax, timeline, joint, picks)
        _joint_force(f_ax, timeline, joint, picks)
        for ax in (q_ax, f_ax):
            _shade(ax, spans)
        if row == 1:
            _key(strip, q_ax)
            f_ax.set_title("answered generalized force (qfrc_inverse)", fontsize=9, loc="left")
            q_ax.set_title("measured q against the answered q", fontsize=9, loc="left")
    bottom = len(joints) + 1
    network, server, nis = (figure.add_subplot(grid[bottom + i, :], sharex=strip) for i in range(3))
    _network(network, timeline, picks, dt=dt, realtime=realtime)
    _server(server, timeline, picks, dt)
    _nis(nis, timeline, picks)
    for ax in (network, server, nis):
        _shade(ax, spans)
        _legend(ax)
    for ax in figure.axes:
        ax.tick_params(labelsize=7)
    for ax in figure.axes[1:-3]:
        # The joint panels are narrower than the panels below: the last row gets its own time labels.
        ax.tick_params(labelbottom=ax in figure.axes[-5:-3])
    for ax in (strip, network, server):
        ax.tick_params(labelbottom=False)
    for ax in figure.axes[1:]:
        # Thousands of points stay one image inside an SVG (--out x.html), not an element each.
        for artist in (*ax.lines, *ax.collections):
            artist.set_rasterized(True)
    nis.set_xlabel("t (s, client clock)", fontsize=8)
    figure.suptitle("\n".join(title), fontsize=10, x=0.01, ha="left")
    return figure
