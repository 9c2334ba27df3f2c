"""`jitdyn sessions plot ID`: one stored session as a PNG, or as one self-contained HTML page (the
figure as inline SVG and a table of the session's facts; no server, no script).

    plotted = plot_session(session_id, data_root=root, engine=engine, out=None, joints=[])
    plotted.path, plotted.notes         # the file written, and what to tell the user

The session is read where the index says (storage.stored), as `sessions export` reads it; what is
drawn is storage.timeline's view of its rows (cli/session_figure.py). Why SVG in HTML and no
plotting library: docs/decisions/0130-session-plot.md.
"""

from __future__ import annotations

import html
import io
import os
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Final

import sqlalchemy as sa

from jitdyn.errors import FailedPrecondition, InvalidArgument, NotFound
from jitdyn.storage.index import SessionIndex, SessionRow
from jitdyn.storage.joints import Joint, choose_joints, stored_joints
from jitdyn.storage.stored import read_stored
from jitdyn.storage.summary import format_counts
from jitdyn.storage.timeline import TIMELINE_COLUMNS, Timeline, session_timeline
from jitdyn.vocabulary import Clock

__all__ = ["FORMATS", "Plotted", "plot_session"]

FORMATS: Final = (".png", ".html")
_DPI: Final = 100


@dataclass(frozen=True)
class Plotted:
    """What was drawn: the file, and the lines that tell the user what they see."""

    path: Path
    notes: tuple[str, ...]


def _target(out: Path | None, session_id: str) -> Path:
    """The file to write: `out`, or `<id>.png` in it when it is a folder, or in the current folder."""
    if out is None:
        return Path(f"{session_id}.png")
    if out.is_dir():
        return out / f"{session_id}.png"
    if out.suffix.lower() not in FORMATS:
        raise InvalidArgument(f"--out must name a {' or '.join(FORMATS)} file, got {out.name!r}")
    if not out.parent.is_dir():
        raise InvalidArgument(f"the folder of --out {out} does not exist")
    return out


def _row(session_id: str, *, engine: sa.Engine, data_root: Path) -> SessionRow:
    try:
        return SessionIndex(engine).get(session_id, tenant="")
    except NotFound:
        raise NotFound(
            f"no session {session_id!r} in {data_root.resolve()}; list them with `jitdyn sessions list`"
        ) from None


def _empty(row: SessionRow, timeline: Timeline) -> str:
    rejected = timeline.rejections.reason
    if rejected.size:
        reasons = ", ".join(f"{reason} {int((rejected == reason).sum())}" for reason in sorted(set(rejected)))
        return f"session {row.session_id} ({row.status}) answered no tick: its {rejected.size} frames were rejected ({reasons})"
    return f"session {row.session_id} ({row.status}) is empty: no tick was answered, nothing to plot"


def _title(row: SessionRow, notes: Sequence[str]) -> list[str]:
    counts = " ".join(format_counts(row.summary).split())
    head = (
        f"session {row.session_id}  ·  {row.model_name} v{row.model_version}  ·  {row.scenario} {row.clock}, "
        f"dt {row.dt * 1e3:g} ms  ·  {row.status}  ·  started {row.started_at:%Y-%m-%d %H:%M:%S}"
    )
    return [head, counts, *notes]


def _html(row: SessionRow, svg: str, title: Sequence[str]) -> str:
    svg = re.sub(r"^.*?(<svg\b)", r"\1", svg, flags=re.DOTALL)  # the XML prolog and doctype
    svg = re.sub(r'(<svg\b[^>]*?)\s(width|height)="[^"]*"', r"\1", svg, count=1)
    svg = re.sub(r'(<svg\b[^>]*?)\s(width|height)="[^"]*"', r"\1", svg, count=1)
    facts = [
        ("session", row.session_id),
        ("model", f"{row.model_name} v{row.model_version} ({row.model_id})"),
        ("scenario, clock", f"{row.scenario}, {row.clock}"),
        ("dt", f"{row.dt * 1e3:g} ms"),
        ("status", row.status),
        ("started", f"{row.started_at:%Y-%m-%d %H:%M:%S %Z}"),
        ("ended", f"{row.ended_at:%Y-%m-%d %H:%M:%S %Z}" if row.ended_at else ""),
        *(
            (label, str(getattr(row.summary, name)))
            for label, name in (
                ("ticks", "ticks"),
                ("measured", "measured"),
                ("predicted", "predicted"),
                ("corrected", "corrected"),
                ("rejected", "rejected"),
                ("late", "late"),
            )
        ),
        ("mean compute", f"{row.summary.mean_compute_us:.0f} µs"),
    ]
    rows = "\n".join(f"<tr><th>{html.escape(k)}</th><td>{html.escape(v)}</td></tr>" for k, v in facts)
    notes = "".join(f"<p>{html.escape(line)}</p>" for line in title[2:])
    return f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8">
<title>jitdyn session {html.escape(row.session_id)}</title>
<style>body{{font-family:sans-serif;margin:1em}} table{{border-collapse:collapse;margin-bottom:1em}}
th,td{{text-align:left;padding:2px 10px;border-bottom:1px solid #ddd}} svg{{width:100%;height:auto}}</style>
</head><body>
<h1 style="font-size:1.2em">jitdyn session {html.escape(row.session_id)}</h1>
<table>
{rows}
</table>
{notes}
{svg}
</body></html>
"""


def plot_session(
    session_id: str,
    *,
    data_root: Path,
    engine: sa.Engine,
    out: Path | None,
    joints: Sequence[str],
    environ: Mapping[str, str] | None = None,
) -> Plotted:
    """Draw the session to `out` (.png or .html; default `<id>.png` here); returns what was written.

    Raises NotFound for an unknown session, FailedPrecondition for one with no Parquet file yet or
    no tick, InvalidArgument for an unknown --out extension or joint name, Unavailable when its
    data root does not answer.
    """
    from jitdyn.cli.session_figure import decimation, draw_session

    target = _target(out, session_id)
    row = _row(session_id, engine=engine, data_root=data_root)
    metadata, table = read_stored(
        row,
        data_root=data_root,
        environ=os.environ if environ is None else environ,
        purpose="plot",
        columns=TIMELINE_COLUMNS,
    )
    every = stored_joints(metadata)
    chosen: list[Joint] = choose_joints(every, joints, model=row.model_name)
    timeline = session_timeline(table)
    if len(timeline.t) == 0:
        raise FailedPrecondition(_empty(row, timeline))
    notes: list[str] = []  # in the figure's title
    told: list[str] = []  # on the terminal, where the names of the joints left out fit
    if not joints and len(every) > len(chosen):
        left = ", ".join(j.name for j in every[len(chosen) :])
        choose = f"{len(chosen)} of {len(every)} joints drawn"
        notes.append(f"{choose} (choose with --joints NAME ...)")
        told.append(f"{choose}; left out: {left} (choose with --joints NAME ...)")
    decimated = decimation(len(timeline.t)).note
    if decimated:
        notes.append(decimated)
        told.append(decimated)
    title = _title(row, notes)
    figure = draw_session(timeline, chosen, title=title, dt=row.dt, realtime=row.clock == Clock.REALTIME)
    tmp = target.with_name(f".{target.name}.tmp")
    try:
        if target.suffix.lower() == ".html":
            buffer = io.StringIO()
            figure.savefig(buffer, format="svg", dpi=_DPI, metadata={"Title": title[0]})
            tmp.write_text(_html(row, buffer.getvalue(), title), encoding="utf-8")
        else:
            figure.savefig(tmp, format="png", dpi=_DPI, metadata={"Title": title[0]})
        os.replace(tmp, target)
    finally:
        tmp.unlink(missing_ok=True)
    return Plotted(path=target, notes=tuple(told))
