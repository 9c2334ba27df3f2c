"""jitdyn's server, in three layers, each importing only those below it:

    transport/   the gRPC edge: servicers, auth, status mapping, message conversion, create_server
    runtime/     the session runtime: ticks, the clock, timewarp, shared services (no protobuf)
    estimation/  the filter, sigma points, propagation and its pool, dead reckoning, dynamics (no gRPC)

Below the server: jitdyn.registry, jitdyn.storage and the contract (jitdyn.v1, jitdyn.errors).
"""
