"""The raw HTTP/2 bytes of one gRPC health check, for HAProxy's `tcp-check send-binary`.

HAProxy 2.6's `http-check` cannot send a gRPC body (no NUL bytes in `body`), so haproxy.cfg sends
these frames over TCP and expects the SERVING answer. Standard library only, so an operator can run
it anywhere; tests/cluster/test_health_frames.py decodes its output with the h2 project's own
parsers and checks haproxy.cfg carries exactly these bytes.

    python deploy/haproxy/grpc_health_frames.py [SERVICE]   # prints the haproxy.cfg lines
"""

from __future__ import annotations

import struct
import sys

PREFACE = b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n"
SERVICE = "jitdyn.v1.DynamicsService"
AUTHORITY = "jitdyn"

FRAME_DATA, FRAME_HEADERS, FRAME_SETTINGS = 0x0, 0x1, 0x4
FLAG_END_STREAM, FLAG_END_HEADERS = 0x1, 0x4
STREAM = 1


def frame(kind: int, flags: int, stream: int, payload: bytes) -> bytes:
    """One HTTP/2 frame (RFC 9113 section 4.1): 24-bit length, type, flags, 31-bit stream id."""
    return struct.pack(">I", len(payload))[1:] + bytes([kind, flags]) + struct.pack(">I", stream) + payload


def _string(value: str) -> bytes:
    # HPACK string literal, not Huffman-coded; every string here is shorter than 127 bytes.
    raw = value.encode()
    if len(raw) >= 127:
        raise ValueError(f"HPACK strings here must be shorter than 127 bytes, got {len(raw)}")
    return bytes([len(raw)]) + raw


def header_block(path: str) -> bytes:
    """The request headers in HPACK (RFC 7541) without the dynamic table: static-table entries and
    literals "without indexing", so the bytes depend on nothing but the values."""
    return b"".join(
        (
            b"\x83",  # :method POST, static index 3
            b"\x86",  # :scheme http, static index 6
            b"\x04" + _string(path),  # :path, name from static index 4
            b"\x01" + _string(AUTHORITY),  # :authority, name from static index 1
            b"\x0f\x10" + _string("application/grpc"),  # content-type, static index 31
            b"\x00" + _string("te") + _string("trailers"),  # te, a new name
        )
    )


def grpc_message(payload: bytes) -> bytes:
    """gRPC's length-prefixed message: not compressed, 32-bit length, the protobuf bytes."""
    return b"\x00" + struct.pack(">I", len(payload)) + payload


def health_request(service: str) -> bytes:
    """grpc.health.v1.HealthCheckRequest{service} in protobuf: field 1, length-delimited."""
    return b"\x0a" + _string(service)


def request_frames(service: str = SERVICE) -> list[tuple[str, bytes]]:
    """What the check sends, frame by frame, with a name for each."""
    return [
        ("connection preface", PREFACE),
        ("SETTINGS, empty", frame(FRAME_SETTINGS, 0, 0, b"")),
        (
            "HEADERS POST /grpc.health.v1.Health/Check",
            frame(FRAME_HEADERS, FLAG_END_HEADERS, STREAM, header_block("/grpc.health.v1.Health/Check")),
        ),
        (
            f"DATA HealthCheckRequest{{service: {service!r}}}, END_STREAM",
            frame(FRAME_DATA, FLAG_END_STREAM, STREAM, grpc_message(health_request(service))),
        ),
    ]


def serving_response() -> bytes:
    """The DATA frame of a SERVING answer on stream 1: HealthCheckResponse{status: SERVING (1)}.
    NOT_SERVING (2) differs in the last byte, so the check fails for a draining replica too."""
    return frame(FRAME_DATA, 0, STREAM, grpc_message(b"\x08\x01"))


def config_lines(service: str = SERVICE) -> list[str]:
    """The `tcp-check` lines of haproxy.cfg's backend."""
    lines = ["tcp-check connect"]
    for name, data in request_frames(service):
        lines.append(f"# {name}")
        lines.append(f"tcp-check send-binary {data.hex()}")
    lines.append("# DATA HealthCheckResponse{status: SERVING} on stream 1")
    lines.append(f"tcp-check expect binary {serving_response().hex()}")
    return lines


if __name__ == "__main__":
    print("\n".join(config_lines(*sys.argv[1:2])))
