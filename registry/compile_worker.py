"""The process registry.compile runs MuJoCo's compiler in, so that a compile can be killed.

Run as `python compile_worker.py FD MEMORY`, FD a connected socket inherited from the parent, MEMORY
the address space the process may use (RLIMIT_AS, bytes; 0 for no limit). It answers b"R" once
ready, then for each (mjcf, assets, max_bytes) job, pickled by the parent, b"M" and the compiled
model in MuJoCo's binary format (MJB), b"B" and the decimal size when the compiled model is larger
than max_bytes (it is then never sent), b"O" when compiling ran out of the memory limit, or b"E" and
MuJoCo's error message. The answer is plain bytes
so that the parent never unpickles what a process that parsed untrusted input wrote. Nothing is
written to stdout, where MuJoCo prints its warnings. Only MuJoCo and numpy are imported here.
"""

from __future__ import annotations

import resource
import signal
import sys
from multiprocessing.connection import Connection

import mujoco
import numpy as np


def _peak_address_space() -> int:
    """The most address space this process has mapped (VmPeak), in bytes."""
    with open("/proc/self/status") as status:
        for line in status:
            if line.startswith("VmPeak:"):
                return int(line.split()[1]) * 1024
    return 0


def main(argv: list[str]) -> int:
    # The parent owns Ctrl-C; a worker ends when its socket closes or it is killed.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    # MuJoCo's default would also append its warnings to MUJOCO_LOG.TXT in the working folder.
    mujoco.set_mju_user_warning(lambda message: print(f"MuJoCo warning: {message}", file=sys.stderr))
    connection = Connection(int(argv[1]))
    memory = int(argv[2]) if len(argv) > 2 else 0
    if memory:
        # Set after the imports, which map more than a compile needs.
        resource.setrlimit(resource.RLIMIT_AS, (memory, memory))
    connection.send_bytes(b"R")
    while True:
        try:
            job = connection.recv()
        except EOFError:
            return 0
        if job is None:
            return 0
        mjcf, assets, max_bytes = job
        try:
            model = mujoco.MjModel.from_xml_string(mjcf, assets=assets)
        except MemoryError:
            connection.send_bytes(b"O")
            return 0
        except Exception as error:  # noqa: BLE001 - MuJoCo reports every compile error as an exception
            # MuJoCo reports a failed allocation as an untyped error, and is not fit to compile again
            # after one: a compile that failed having mapped more than half the memory limit is
            # taken for one, answered "O", and this process ends.
            if memory and _peak_address_space() > memory // 2:
                connection.send_bytes(b"O")
                return 0
            connection.send_bytes(b"E" + str(error).encode("utf-8", "replace"))
            continue
        size = mujoco.mj_sizeModel(model)
        if size > max_bytes:
            del model
            connection.send_bytes(b"B%d" % size)
            continue
        buffer = np.empty(size, dtype=np.uint8)
        mujoco.mj_saveModel(model, None, buffer)
        connection.send_bytes(b"M" + buffer.tobytes())


if __name__ == "__main__":
    sys.exit(main(sys.argv))
