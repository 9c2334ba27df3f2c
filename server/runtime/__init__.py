"""The session runtime: opening a session (`opening`, from a checked `plan`), one session's ticks
and timewarp (`session`), the REALTIME clock (`clock`, `alarm`), checked frames (`frames`), the
limits and admission of sessions (`limits`, `admission`, `switch_interval`) and the services every
session shares (`services`). It imports estimation, registry and storage; never grpc or the
generated messages.
"""
