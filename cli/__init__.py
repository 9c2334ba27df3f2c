"""The `jitdyn` command line, the top of the tree: it drives the server, the client, the storage
and the research harness, and nothing imports it.
"""

import os

# gRPC's C core logs to stderr on its own (a busy port is one "E... add_port.cc" line before the
# exception the CLI turns into its one-line message). It reads this only when grpc is imported,
# which is below; GRPC_VERBOSITY=error in the environment brings its logs back.
os.environ.setdefault("GRPC_VERBOSITY", "NONE")

from jitdyn.cli.main import build_parser, main

__all__ = ["build_parser", "main"]
