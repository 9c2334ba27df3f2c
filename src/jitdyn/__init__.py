"""jitdyn: cloud, just-in-time MuJoCo dynamics of biomechanical models over gRPC.

The one installed namespace, its layers importing downwards only (tests/test_layers.py checks it):

    jitdyn.cli          the `jitdyn` command
    jitdyn.experiments  the research harness: objects, network emulation, metrics, thesis reports
    jitdyn.client       the Python SDK (sync and async) and model packing
    jitdyn.server       transport > runtime > estimation
    jitdyn.registry, jitdyn.storage
    jitdyn.v1, jitdyn.errors, jitdyn.checksum   the contract: imports nothing of ours
    jitdyn.models       the built-in MJCF files
"""
