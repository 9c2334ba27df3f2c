"""jitdyn.compliance: the contract's conformance cases, run against any server that implements
proto/jitdyn/v1, as dm_env_rpc's compliance tests and gRPC's interop client are.

    python -m jitdyn.compliance --server 127.0.0.1:50051 [--api-key KEY] [--case NAME ...]

It talks to the server through the generated stubs (jitdyn.v1) only, with its own checks: it
registers its own two models, recomputes the contract's checksum and content id from proto/'s
words, and never imports the server (docs/decisions/0176-compliance-speaks-the-contract-only.md).
docs/compliance.md lists the cases.
"""

from __future__ import annotations

from jitdyn.compliance.run import Report, run

__all__ = ["Report", "run"]
