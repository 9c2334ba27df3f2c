"""The gRPC edge of the server: `create_server` and `serve`, the three servicers, API-key auth, the
one mapping of jitdyn's exceptions to statuses, and the conversions between messages and the
runtime's values. The only part of the server that imports grpc.
"""
