"""The process registry.compile runs MuJoCo's compiler in, so that a compile can be killed.

Run as `python compile_worker.py FD`, FD a connected socket inherited from the parent. It answers
b"R" once ready, then for each (mjcf, assets) job, pickled by the parent, b"M" and the compiled
model in MuJoCo's binary format (MJB), or b"E" and MuJoCo's error message. The answer is plain bytes
so that the parent never unpickles what a process that parsed untrusted input wrote. Nothing is
written to stdout, where MuJoCo prints its warnings. Only MuJoCo and numpy are imported here.
"""

from __future__ import annotations

import signal
import sys
from multiprocessing.connection import Connection

import mujoco
import numpy as np


def main(argv: list[str]) -> int:
    # The parent owns Ctrl-C; a worker ends when its socket closes or it is killed.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    # MuJoCo's default would also append its warnings to MUJOCO_LOG.TXT in the working folder.
    mujoco.set_mju_user_warning(lambda message: print(f"MuJoCo warning: {message}", file=sys.stderr))
    connection = Connection(int(argv[1]))
    connection.send_bytes(b"R")
    while True:
        try:
            job = connection.recv()
        except EOFError:
            return 0
        if job is None:
            return 0
        mjcf, assets = job
        try:
            model = mujoco.MjModel.from_xml_string(mjcf, assets=assets)
        except Exception as error:  # noqa: BLE001 - MuJoCo reports every compile error as an exception
            connection.send_bytes(b"E" + str(error).encode("utf-8", "replace"))
            continue
        buffer = np.empty(mujoco.mj_sizeModel(model), dtype=np.uint8)
        mujoco.mj_saveModel(model, None, buffer)
        connection.send_bytes(b"M" + buffer.tobytes())


if __name__ == "__main__":
    sys.exit(main(sys.argv))
