"""The session runtime: one session's ticks and timewarp (`session`), the REALTIME clock
(`clock`), checked frames (`frames`) and the services every session shares (`services`).
It imports estimation, registry and storage; never grpc or the generated messages.
"""
