"""Running chosen cases against a target, and the table of their outcomes.

report = run(Target("127.0.0.1:50051"), names=["frame.shape"])
print("\\n".join(report.table()))
report.failed          # the names of the cases that failed
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass

# The cases register themselves as their modules are imported, in this order.
from jitdyn.compliance import ending, opening, streaming
from jitdyn.compliance.suite import CASES, Case, Context, Outcome, run_case
from jitdyn.compliance.wire import Connection, Target

__all__ = ["Report", "choose", "ordered", "run"]

# The order the cases run and are listed in: the registry and opening, the stream, the end.
_ORDER = tuple(module.__name__ for module in (opening, streaming, ending))


def ordered() -> list[Case]:
    """Every case, in _ORDER's order of their modules, then of their definition."""
    return sorted(CASES.values(), key=lambda c: _ORDER.index(c.run.__module__))


@dataclass(frozen=True)
class Report:
    """The outcome of every case run, in order, and the statuses the cases made the server end with."""

    outcomes: tuple[Outcome, ...]
    provoked: frozenset[str]

    @property
    def failed(self) -> list[str]:
        return [o.name for o in self.outcomes if o.result == "fail"]

    def table(self) -> Iterator[str]:
        """Aligned lines: a header, a rule, a row a case, and a line of totals."""
        rows = [(o.name, o.result.upper(), f"{o.seconds:.1f}", o.note) for o in self.outcomes]
        header = ("case", "result", "s", "note")
        widths = [max(len(r[i]) for r in [header, *rows]) for i in range(3)]
        for row in [header, tuple("-" * w for w in widths) + ("-" * 4,), *rows]:
            yield "  ".join(
                [row[0].ljust(widths[0]), row[1].ljust(widths[1]), row[2].rjust(widths[2]), row[3]]
            ).rstrip()
        counts = {
            result: sum(o.result == result for o in self.outcomes) for result in ("pass", "fail", "skip")
        }
        yield f"{counts['pass']} passed, {counts['fail']} failed, {counts['skip']} skipped"
        yield "statuses provoked: " + ", ".join(sorted(self.provoked))


def choose(names: Sequence[str]) -> list[Case]:
    """The cases named (a name, or a prefix ending in "." for a group), in suite order; all when
    none is named. ValueError naming the unknown ones."""
    if not names:
        return ordered()
    unknown = [
        n for n in names if n not in CASES and not any(c.startswith(n) and n.endswith(".") for c in CASES)
    ]
    if unknown:
        raise ValueError(
            f"no case named {', '.join(unknown)}; the cases: {', '.join(c.name for c in ordered())}"
        )
    return [
        c
        for c in ordered()
        if c.name in names or any(n.endswith(".") and c.name.startswith(n) for n in names)
    ]


def run(
    target: Target,
    *,
    names: Sequence[str] = (),
    other_key: str | None = None,
    admission_wait: float = 30.0,
    progress: Callable[[Outcome], None] | None = None,
    connect_timeout: float = 10.0,
) -> Report:
    """Run the chosen cases (all by default) against `target`, one after another."""
    chosen = choose(names)
    outcomes = []
    with Connection(target) as wire:
        wire.ready(connect_timeout)
        ctx = Context(wire=wire, other_key=other_key, admission_wait=admission_wait)
        for one in chosen:
            outcome = run_case(ctx, one)
            outcomes.append(outcome)
            if progress is not None:
                progress(outcome)
    return Report(outcomes=tuple(outcomes), provoked=frozenset(ctx.provoked))
