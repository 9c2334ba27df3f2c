"""The `jitdyn` command line, the top of the tree: it drives the server, the client, the storage
and the research harness, and nothing imports it.
"""

from jitdyn.cli.main import build_parser, main

__all__ = ["build_parser", "main"]
