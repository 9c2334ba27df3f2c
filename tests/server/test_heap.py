"""The garbage collector's pauses reach the metrics without ever waiting for a lock the collection
interrupted (server/runtime/heap.py)."""

from __future__ import annotations

import subprocess
import sys
import textwrap

# The server's wiring (app.serve: the pauses kept by watch_collections, observed from the loop by
# observe_collections), in a process whose collector runs at nearly every allocation, while a
# thread makes labelled series in prometheus-client's multiprocess mode: it holds one
# non-reentrant lock while it allocates. A collector callback that observed a metric itself waited
# there for its own lock forever (a `jitdyn serve` process hung so, its sessions opening).
_SCRIPT = textwrap.dedent(
    """
    import asyncio, gc, os, sys, tempfile, threading
    os.environ["PROMETHEUS_MULTIPROC_DIR"] = tempfile.mkdtemp()
    from jitdyn.server.runtime.heap import watch_collections
    from jitdyn.server.transport.app import observe_collections
    from jitdyn.server.transport.metrics import metrics

    def make_series():
        for i in range(300):
            metrics().compute.labels(str(i), "pendulum")

    async def main():
        task = asyncio.create_task(observe_collections(watch_collections(), every=0.01))
        gc.set_threshold(1, 1, 1)
        thread = threading.Thread(target=make_series)
        thread.start()
        while thread.is_alive():
            await asyncio.sleep(0.01)
        await asyncio.sleep(0.05)
        gc.set_threshold(700, 10, 10)
        task.cancel()
        samples = [s for m in metrics().gc_pause.collect() for s in m.samples]
        print(int(sum(s.value for s in samples if s.name.endswith("_count"))))

    asyncio.run(main())
    """
)


def test_a_collection_inside_a_metric_lock_does_not_hang_the_process() -> None:
    try:
        done = subprocess.run(
            [sys.executable, "-c", _SCRIPT], capture_output=True, text=True, timeout=60, check=False
        )
    except subprocess.TimeoutExpired:
        raise AssertionError("the process hung: a collector callback waited for a metric's lock") from None
    assert done.returncode == 0, done.stderr
    # Collections happened and every pause was observed (hundreds, at a threshold of 1).
    assert int(done.stdout.strip()) > 100, done.stdout
