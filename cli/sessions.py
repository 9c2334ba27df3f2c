"""`jitdyn sessions list | show | query | export`: the stored sessions, from the data folder and
the SQL index, without a server."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import pyarrow.csv as pacsv

from jitdyn.errors import FailedPrecondition
from jitdyn.storage.db import default_index_url, open_index
from jitdyn.storage.export import export_session
from jitdyn.storage.index import SessionIndex, SessionRow
from jitdyn.storage.query import run_query

__all__ = ["run_sessions_command"]


def _engine(args: argparse.Namespace):  # type: ignore[no-untyped-def]
    data_root: Path = args.data
    if not args.index and not (data_root / "index.sqlite").exists():
        raise FailedPrecondition(
            f"no jitdyn data in {data_root.resolve()}: give --data (or JITDYN_DATA) of a server's data "
            "folder, or --index of its SQL index"
        )
    return open_index(args.index or default_index_url(data_root))


def _line(row: SessionRow) -> str:
    s = row.summary
    return (
        f"{row.session_id}  {row.started_at:%Y-%m-%d %H:%M:%S}  {row.status:<9}  {row.model_name} v{row.model_version}  "
        f"{row.scenario.lower():<10} {row.clock.lower():<8} ticks {s.ticks:>6}  measured {s.measured:>6}  "
        f"predicted {s.predicted:>5}  corrected {s.corrected:>4}  rejected {s.rejected:>4}"
    )


def run_sessions_command(args: argparse.Namespace) -> int:
    engine = _engine(args)
    data_root: Path = args.data
    if args.sessions_command == "list":
        index = SessionIndex(engine)
        rows, _ = index.list(tenant="", model_name=args.model, status=args.status, page_size=args.limit)
        if not rows:
            print("no sessions", file=sys.stderr)
        for row in rows:
            print(_line(row))
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
            "location": str(data_root / row.location) if row.location else "",
        }
        print(json.dumps(details, indent=2, default=str))
    elif args.sessions_command == "query":
        table = run_query(args.sql, data_root=data_root, engine=engine)
        if args.csv:
            pacsv.write_csv(table, args.csv)
            print(f"{table.num_rows} rows written to {args.csv}", file=sys.stderr)
        else:
            print(table.to_pandas().to_string() if _has_pandas() else table.to_string(preview_cols=20))
    else:
        out = args.out or Path(f"{args.session_id}.{args.format}")
        path = export_session(args.session_id, data_root=data_root, engine=engine, fmt=args.format, out=out)
        print(f"exported {args.session_id} as {args.format} to {path}")
    return 0


def _has_pandas() -> bool:
    try:
        import pandas  # noqa: F401
    except ImportError:
        return False
    return True
