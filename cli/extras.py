"""The optional parts of jitdyn (pyproject.toml's extras), as the commands that need them check for
them: before doing anything, and with the `pip install` that fixes it."""

from __future__ import annotations

__all__ = ["MissingExtra", "require_extra"]


class MissingExtra(Exception):
    """A command needs an optional part of jitdyn that is not installed."""

    def __init__(self, what: str, extra: str) -> None:
        super().__init__(f"needs {what}, which is not installed: pip install 'jitdyn[{extra}]'")


def require_extra(module: str, *, what: str, extra: str) -> None:
    """Raise MissingExtra unless `module` imports."""
    try:
        __import__(module)
    except ImportError:
        raise MissingExtra(what, extra) from None
