"""`jitdyn sessions list | show | query | export | plot | render`: the stored sessions, from the data folder and
the SQL index, without a server. Counts are shown by storage.summary.format_counts, as the demo
shows them, so that the two agree.

A session on a data root is read where the index says (its URI), so that any machine with the
index (`--index`) and the root's settings (AWS_* for S3) sees every replica's sessions.
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import datetime
import json
import math
import sys
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from operator import attrgetter
from pathlib import Path
from typing import Any, Final, TextIO

import sqlalchemy as sa

from jitdyn.cli.extras import require_extra
from jitdyn.errors import FailedPrecondition, NotFound
from jitdyn.settings import Settings
from jitdyn.storage.db import default_index_url, open_index
from jitdyn.storage.index import MAX_PAGE_SIZE, SessionIndex, SessionRow
from jitdyn.storage.root import is_uri
from jitdyn.storage.summary import COUNTS, format_counts

__all__ = ["format_table", "run_sessions_command"]

# Lists longer than this are shown as their first elements and a count, in the table format only.
_LIST_SHOWN = 4


def _engine(settings: Settings) -> sa.Engine:
    data_root = settings.data
    if not settings.index_url and not (data_root / "index.sqlite").exists():
        raise FailedPrecondition(
            f"no jitdyn data in {data_root.resolve()}: give --data (or JITDYN_DATA) of a server's data "
            "folder, or --index of its SQL index"
        )
    return open_index(settings.index_url or default_index_url(data_root))


def _where(location: str, data_root: Path) -> str:
    """A data root's URI as the index holds it; a path in the data folder made absolute."""
    if not location or is_uri(location):
        return location
    return str((data_root / location).resolve())


@dataclass(frozen=True)
class _Column:
    header: str
    value: Callable[[SessionRow], Any]


# `sessions list`'s columns; the counts are those of storage.summary.COUNTS, as the demo prints them.
_LIST_COLUMNS: Final = (
    _Column("id", lambda row: row.session_id),
    _Column("started", lambda row: f"{row.started_at:%Y-%m-%d %H:%M:%S}"),
    _Column("status", lambda row: row.status),
    _Column("model", lambda row: f"{row.model_name} v{row.model_version}"),
    _Column("scenario", lambda row: row.scenario),
    _Column("clock", lambda row: row.clock),
    *(_Column(label, attrgetter(f"summary.{name}")) for label, name, _ in COUNTS),
)


def _list(engine: sa.Engine, args: argparse.Namespace) -> None:
    """The sessions as a table with a header, newest first; a filter that matches none says which
    models the index has sessions of."""
    wanted = args.model
    index = SessionIndex(engine)
    rows, _ = index.list(
        tenant="",
        model_name=wanted.name or None if wanted else None,
        model_version=wanted.version or None if wanted else None,
        model_id=wanted.model_id or None if wanted else None,
        status=args.status,
        page_size=args.limit,
    )
    if rows:
        table = [[column.value(row) for column in _LIST_COLUMNS] for row in rows]
        print("\n".join(format_table([column.header for column in _LIST_COLUMNS], table)))
        return
    if wanted is None and args.status is None:
        print("no sessions", file=sys.stderr)
        return
    everything, _ = index.list(tenant="", page_size=MAX_PAGE_SIZE)
    models = sorted({f"{row.model_name} v{row.model_version}" for row in everything})
    some = (
        f"the newest {MAX_PAGE_SIZE} sessions" if len(everything) == MAX_PAGE_SIZE else "the stored sessions"
    )
    held = f"{some} are of {', '.join(models)}" if models else "no session is stored"
    print(f"no sessions match; {held}", file=sys.stderr)


def _line(row: SessionRow) -> str:
    return (
        f"{row.session_id}  {row.started_at:%Y-%m-%d %H:%M:%S}  {row.status:<9}  {row.model_name} v{row.model_version}  "
        f"{row.scenario:<10} {row.clock:<8} {format_counts(row.summary)}"
    )


def _cell(value: Any) -> str:
    if value is None:
        return ""
    if isinstance(value, float):
        return "nan" if math.isnan(value) else f"{value:.6g}"
    if isinstance(value, datetime.datetime):
        return value.isoformat(sep=" ", timespec="milliseconds")
    if isinstance(value, list):
        shown = ", ".join(_cell(v) for v in value[:_LIST_SHOWN])
        more = f", ... ({len(value)})" if len(value) > _LIST_SHOWN else ""
        return f"[{shown}{more}]"
    if isinstance(value, dict):
        return json.dumps(value, default=str)
    return str(value)


def format_table(columns: list[str], rows: list[list[Any]]) -> Iterator[str]:
    """Lines of an aligned text table: a header, a rule, the rows; numeric columns right-aligned."""
    cells = [[_cell(value) for value in row] for row in rows]
    numeric = [
        all(
            isinstance(row[i], (int, float)) and not isinstance(row[i], bool)
            for row in rows
            if row[i] is not None
        )
        for i in range(len(columns))
    ]
    widths = [max([len(c), *(len(r[i]) for r in cells)]) for i, c in enumerate(columns)]

    def line(values: list[str]) -> str:
        return "  ".join(
            v.rjust(w) if right else v.ljust(w) for v, w, right in zip(values, widths, numeric, strict=True)
        ).rstrip()

    yield line(columns)
    yield "  ".join("-" * w for w in widths)
    for r in cells:
        yield line(r)


def _write_query(table: Any, fmt: str, out: TextIO) -> None:
    columns: list[str] = list(table.column_names)
    rows: list[list[Any]] = [list(row) for row in zip(*(c.to_pylist() for c in table.columns), strict=True)]
    if fmt == "csv":
        # Lists and maps (qpos, attributes) as JSON in one cell: CSV has no nested values.
        writer = csv.writer(out, lineterminator="\n")
        writer.writerow(columns)
        for row in rows:
            writer.writerow(
                [
                    json.dumps(v, default=str) if isinstance(v, (list, dict)) else "" if v is None else v
                    for v in row
                ]
            )
    elif fmt == "json":
        for row in rows:
            out.write(json.dumps(dict(zip(columns, row, strict=True)), default=str) + "\n")
    else:
        out.writelines(text + "\n" for text in format_table(columns, rows))


def _render(args: argparse.Namespace, settings: Settings) -> int:
    from jitdyn.cli.render import RenderRequest, render_session

    request = RenderRequest(
        session_id=args.session_id,
        data_root=settings.data,
        index_url=settings.index_url or default_index_url(settings.data),
        out=args.out,
        frame=args.frame,
    )
    rendered = render_session(request, gl=args.gl)
    for note in rendered.notes:
        print(note, file=sys.stderr)
    print(f"rendered {args.session_id} to {rendered.path}")
    return 0


def _export_mcap(args: argparse.Namespace, *, data_root: Path, engine: sa.Engine) -> None:
    from jitdyn.cli.mcap_export import export_mcap

    exported = export_mcap(
        args.session_id, data_root=data_root, engine=engine, out=args.out or Path(f"{args.session_id}.mcap")
    )
    channels = ", ".join(f"{topic} {count}" for topic, count in exported.counts.items())
    print(f"messages by channel: {channels}", file=sys.stderr)
    print(f"exported {args.session_id} as mcap to {exported.path}")


def run_sessions_command(args: argparse.Namespace, settings: Settings) -> int:
    if args.sessions_command == "query":
        # Checked before reading anything: the query needs DuckDB, an extra.
        require_extra("duckdb", what="DuckDB", extra="query")
    elif args.sessions_command == "plot":
        require_extra("matplotlib", what="matplotlib (plots)", extra="experiments")
    elif args.sessions_command == "render":
        require_extra("PIL", what="Pillow (frames and captions)", extra="render")
    elif args.sessions_command == "export" and args.format == "mcap":
        require_extra("mcap", what="mcap (MCAP files)", extra="lab")
    engine = _engine(settings)
    data_root: Path = settings.data
    if args.sessions_command in ("show", "export", "plot", "render"):
        # The start of an id will do, as for a git commit, when only one session's id starts so;
        # an id nobody's starts with is left to the command, which says it is not there.
        with contextlib.suppress(NotFound):
            args.session_id = SessionIndex(engine).complete_id(args.session_id, tenant="")
    if args.sessions_command == "render":
        return _render(args, settings)
    if args.sessions_command == "list":
        _list(engine, args)
    elif args.sessions_command == "show":
        row = SessionIndex(engine).get(args.session_id, tenant="")
        print(_line(row))
        details = {
            "model_id": row.model_id,
            "dt": row.dt,
            "estimator": row.estimator,
            "subject_pseudonym": row.subject_pseudonym,
            "subject_attributes": row.subject_attributes,
            "ended_at": row.ended_at.isoformat() if row.ended_at else None,
            "summary": {k: getattr(row.summary, k) for k in row.summary.__dataclass_fields__},
            "location": _where(row.location, data_root),
        }
        print(json.dumps(details, indent=2, default=str))
    elif args.sessions_command == "query":
        from jitdyn.storage.query import run_query

        table = run_query(args.sql, data_root=data_root, engine=engine)
        if args.out:
            with args.out.open("w", encoding="utf-8", newline="") as out:
                _write_query(table, args.format, out)
            print(f"{table.num_rows} rows written to {args.out}", file=sys.stderr)
        else:
            _write_query(table, args.format, sys.stdout)
    elif args.sessions_command == "plot":
        from jitdyn.cli.plot import plot_session

        plotted = plot_session(
            args.session_id, data_root=data_root, engine=engine, out=args.out, joints=args.joints
        )
        for note in plotted.notes:
            print(note, file=sys.stderr)
        print(f"plotted {args.session_id} to {plotted.path}")
    elif args.format == "mcap":
        _export_mcap(args, data_root=data_root, engine=engine)
    else:
        from jitdyn.storage.export import export_session

        out_path = args.out or Path(f"{args.session_id}.{args.format}")
        path = export_session(
            args.session_id, data_root=data_root, engine=engine, fmt=args.format, out=out_path
        )
        print(f"exported {args.session_id} as {args.format} to {path}")
    return 0
