"""Client processes on this machine, found from their connection, so that admission does not take
a client's own start-up (its imports, its trajectory, its model's compile) for load that refuses it
(docs/decisions/0207-a-clients-start-up-is-not-load.md).

    clients = LocalClients(admission.observe_client, needed=admission.machine_short)
    await clients.look(context.peer())     # on the event loop: a lookup on a thread when wanted

Linux only (/proc): the peer's socket is looked up in /proc/net/tcp and tcp6 by its address and
port, its process by the socket's inode among /proc/PID/fd, and its start and CPU in
/proc/PID/stat. A process in another PID namespace, or of another user whose /proc/PID/fd this
server may not read, is not found: its CPU stays load, the safe side. A lookup reads a few
hundred /proc entries (about 5 ms here), once per connection, off the event loop.
"""

from __future__ import annotations

import asyncio
import ipaddress
import os
import re
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass
from typing import Final

__all__ = ["ClientStart", "LocalClients", "client_start"]

_Address = ipaddress.IPv4Address | ipaddress.IPv6Address
_PEER = re.compile(r"^ipv([46]):\[?([0-9A-Fa-f.:]+?)\]?:(\d+)$")
_ESTABLISHED: Final = "01"


@dataclass(frozen=True, slots=True)
class ClientStart:
    """A client process on this machine: when it started, when it first opened a session here, and
    the CPU it used between the two (monotonic s, s)."""

    pid: int
    started: float
    opened: float
    cpu: float
    born: int = 0  # its start in clock ticks since boot: with pid, which process this is

    def within(self, since: float, until: float) -> float:
        """s of its start-up's CPU that fell in [since, until], taking it as spread evenly over the
        start-up (a client that ran for an hour before opening puts little of it in a window)."""
        overlap = min(until, self.opened) - max(since, self.started)
        if overlap <= 0.0:
            return 0.0
        span = self.opened - self.started
        return self.cpu if span <= 0.0 else self.cpu * min(1.0, overlap / span)


def _parse_peer(peer: str) -> tuple[_Address, int] | None:
    """gRPC's peer string ("ipv4:127.0.0.1:5000", "ipv6:[::1]:5000") as an address and port."""
    found = _PEER.match(peer)
    if found is None:
        return None
    try:
        return ipaddress.ip_address(found.group(2)), int(found.group(3))
    except ValueError:
        return None


def _proc_address(hexed: str) -> tuple[_Address, int]:
    """/proc/net/tcp's "0100007F:1F90": the address in 32-bit words of host order, the port."""
    address, port = hexed.split(":")
    raw = bytes.fromhex(address)
    words = b"".join(raw[i : i + 4][::-1] for i in range(0, len(raw), 4))
    if len(words) == 4:
        return ipaddress.IPv4Address(words), int(port, 16)
    return ipaddress.IPv6Address(words), int(port, 16)


def _same(a: _Address, b: _Address) -> bool:
    """Equal, an IPv4 address and its IPv4-mapped IPv6 form included."""
    a4 = a.ipv4_mapped if isinstance(a, ipaddress.IPv6Address) and a.ipv4_mapped else a
    b4 = b.ipv4_mapped if isinstance(b, ipaddress.IPv6Address) and b.ipv4_mapped else b
    return a4 == b4


def _socket_inode(address: _Address, port: int) -> int | None:
    """The inode of this machine's established TCP socket whose local end is address:port."""
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        try:
            with open(table, encoding="ascii") as lines:
                next(lines, None)  # the header
                for line in lines:
                    fields = line.split()
                    if len(fields) < 10 or fields[3] != _ESTABLISHED:
                        continue
                    local, local_port = _proc_address(fields[1])
                    if local_port == port and _same(local, address):
                        return int(fields[9]) or None
        except (OSError, ValueError):
            continue
    return None


def _owner(inode: int) -> int | None:
    """The process holding socket `inode` open, among those whose descriptors this one may read."""
    target = f"socket:[{inode}]"
    me = os.getpid()
    with os.scandir("/proc") as processes:
        pids = [int(e.name) for e in processes if e.name.isdigit() and int(e.name) != me]
    for pid in pids:
        try:
            with os.scandir(f"/proc/{pid}/fd") as descriptors:
                if any(os.readlink(fd.path) == target for fd in descriptors):
                    return pid
        except OSError:  # gone, or not ours to read
            continue
    return None


def _started_and_cpu(pid: int) -> tuple[float, float, int] | None:
    """(monotonic s when `pid` started, its CPU s so far, its start in clock ticks since boot) from
    /proc/PID/stat."""
    try:
        with open(f"/proc/{pid}/stat", encoding="ascii", errors="replace") as stat:
            text = stat.read()
    except OSError:
        return None
    fields = text[text.rfind(")") + 2 :].split()
    if len(fields) < 20:
        return None
    tick = os.sysconf("SC_CLK_TCK")
    cpu = (int(fields[11]) + int(fields[12])) / tick  # utime, stime
    born = int(fields[19])  # starttime
    clock = getattr(time, "CLOCK_BOOTTIME", time.CLOCK_MONOTONIC)
    return time.monotonic() - (time.clock_gettime(clock) - born / tick), cpu, born


def client_start(peer: str) -> ClientStart | None:
    """The process on this machine at the other end of the connection `peer` (gRPC's
    ServicerContext.peer()), with its start-up until now; None where it is not on this machine, not
    visible to this process, or this is not Linux."""
    parsed = _parse_peer(peer)
    if parsed is None:
        return None
    opened = time.monotonic()
    try:
        inode = _socket_inode(*parsed)
        pid = None if inode is None else _owner(inode)
        found = None if pid is None else _started_and_cpu(pid)
    except (OSError, ValueError):  # no /proc, or one that reads otherwise: nothing is known
        return None
    if pid is None or found is None:
        return None
    started, cpu, born = found
    return ClientStart(pid=pid, started=started, opened=opened, cpu=cpu, born=born)


class LocalClients:
    """The connections whose process was looked for, each once, and what was found told to `tell`
    (Admission.observe_client), once per process: a client's later connections come after its
    start-up, and their CPU since is load. Looked for only while `needed()` (the machine is short
    of CPU), and at most LOOKUPS_PER_SECOND of them (a burst of opens from as many connections
    must not cost seconds of lookups). Thread-safe."""

    _REMEMBERED: Final = 4096  # connections; the oldest are forgotten first
    LOOKUPS_PER_SECOND: Final = 20

    def __init__(self, tell: Callable[[ClientStart], None], *, needed: Callable[[], bool]) -> None:
        self._tell = tell
        self._needed = needed
        self._seen: OrderedDict[str, None] = OrderedDict()
        self._told: OrderedDict[tuple[int, int], None] = OrderedDict()  # (pid, born) of processes
        self._lock = threading.Lock()
        self._second, self._lookups = 0, 0
        self._looking: dict[str, asyncio.Future[None]] = {}  # lookups under way, by connection

    async def look(self, peer: str) -> None:
        """On the event loop: look for the process of `peer` when `wanted`, on a thread, and wait
        for it; the opens of a connection that come while its lookup runs wait for that one."""
        running = self._looking.get(peer)
        if running is not None:
            await asyncio.shield(running)
            return
        if not self.wanted(peer):
            return
        lookup = asyncio.ensure_future(asyncio.to_thread(self.note, peer))
        self._looking[peer] = lookup
        try:
            await asyncio.shield(lookup)
        finally:
            if lookup.done():
                self._looking.pop(peer, None)
            else:  # this open was cancelled; the lookup goes on and cleans up after itself
                lookup.add_done_callback(lambda _: self._looking.pop(peer, None))

    def wanted(self, peer: str) -> bool:
        """Whether to look for the process of connection `peer` now: not looked for yet, the
        machine short of CPU, and lookups left this second."""
        if peer in self._seen or not self._needed():
            return False
        second = int(time.monotonic())
        return second != self._second or self._lookups < self.LOOKUPS_PER_SECOND

    def note(self, peer: str) -> None:
        """Look for the process at the other end of `peer`, once: blocking, a few ms."""
        with self._lock:
            second = int(time.monotonic())
            if second != self._second:
                self._second, self._lookups = second, 0
            if peer in self._seen or self._lookups >= self.LOOKUPS_PER_SECOND:
                return
            self._lookups += 1
            self._seen[peer] = None
            while len(self._seen) > self._REMEMBERED:
                self._seen.popitem(last=False)
        start = client_start(peer)
        if start is None:
            return
        with self._lock:
            if (start.pid, start.born) in self._told:
                return
            self._told[start.pid, start.born] = None
            while len(self._told) > self._REMEMBERED:
                self._told.popitem(last=False)
        self._tell(start)
