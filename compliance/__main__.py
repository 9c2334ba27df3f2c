"""`python -m jitdyn.compliance --server HOST:PORT`: run the conformance cases against a server and
print their table; exit 0 when none failed, 1 when one did (or the server cannot be reached), 2
on a usage error."""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Sequence
from pathlib import Path

from jitdyn.compliance.run import choose, ordered, run
from jitdyn.compliance.suite import CASES, Outcome
from jitdyn.compliance.wire import CaseFailed, Target


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m jitdyn.compliance",
        description="Run the conformance cases of proto/jitdyn/v1 against a server that implements it "
        "(any language): it registers two small models of its own, opens sessions, and checks each "
        "answer and status against the contract. Prints a table of the cases; exit 0 when none "
        "failed, 1 when one did or the server cannot be reached, 2 on a usage error.",
        epilog="Where the contract allows two answers (a late frame CORRECTED or rejected TOO_OLD), "
        "both pass and the note says which came. Environment: JITDYN_API_KEY and "
        "JITDYN_OTHER_API_KEY stand for the two key options.",
    )
    parser.add_argument(
        "--server", metavar="HOST:PORT", help="the server under test (required but with --list)"
    )
    parser.add_argument(
        "--case",
        nargs="+",
        default=[],
        metavar="NAME",
        help="run only these cases (a name, or a group such as `frame.`); --list names them",
    )
    parser.add_argument("--list", action="store_true", help="list the cases and what each checks, then exit")
    parser.add_argument(
        "--api-key",
        default=os.environ.get("JITDYN_API_KEY"),
        metavar="KEY",
        help="the key every call carries (authorization: Bearer KEY); without it the auth cases are skipped",
    )
    parser.add_argument(
        "--other-api-key",
        default=os.environ.get("JITDYN_OTHER_API_KEY"),
        metavar="KEY",
        help="a key of another tenant, for the case that tenants do not see each other's sessions",
    )
    parser.add_argument(
        "--admission-wait",
        type=float,
        default=30.0,
        metavar="SECONDS",
        help="how long a REALTIME open the server refuses for its load (RESOURCE_EXHAUSTED) is tried "
        "again before its case is skipped (default 30)",
    )
    parser.add_argument(
        "--ca-file", type=Path, metavar="FILE", help="PEM of the CA to trust: speak TLS to the server"
    )
    parser.add_argument(
        "-q", "--quiet", action="store_true", help="print the table only, not each case as it ends"
    )
    return parser


def _progress(outcome: Outcome) -> None:
    print(
        f"{outcome.result.upper():<4} {outcome.name} ({outcome.seconds:.1f} s)", file=sys.stderr, flush=True
    )


def main(argv: Sequence[str] | None = None) -> int:
    parser = _parser()
    args = parser.parse_args(argv)
    if args.list:
        width = max(len(name) for name in CASES)
        for one in ordered():
            print(f"{one.name.ljust(width)}  {one.summary}")
        return 0
    if not args.server:
        parser.error("--server HOST:PORT is required: the server to run the cases against")
    try:
        choose(args.case)
    except ValueError as error:
        parser.error(str(error))
    if args.ca_file is not None and not args.ca_file.is_file():
        parser.error(f"--ca-file {args.ca_file}: no such file")
    target = Target(args.server, api_key=args.api_key or None, ca_file=args.ca_file)
    try:
        report = run(
            target,
            names=args.case,
            other_key=args.other_api_key or None,
            admission_wait=args.admission_wait,
            progress=None if args.quiet else _progress,
        )
    except CaseFailed as error:
        print(f"jitdyn.compliance: {error}", file=sys.stderr)
        return 1
    for line in report.table():
        print(line)
    return 1 if report.failed else 0


if __name__ == "__main__":
    sys.exit(main())
