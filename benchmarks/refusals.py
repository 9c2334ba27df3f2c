"""What a refused open costs the server: a burst of REALTIME opens, one connection each as devices
have, against a `jitdyn serve` process with no room for them, side by side in one run with a bare
grpc.aio server that reads the same first message and aborts RESOURCE_EXHAUSTED (gRPC's part of a
refusal, which no server of ours can go below). Alternating rounds, so that the shared machine's
drift falls on both alike. It reports, per round and server:

    server ms/open   the server's CPU (user + system, every process) during the burst / opens
    client ms/open   this program's CPU / opens (the clients' side, which on a deployment is not the
                     server machine's)
    refusals         how many opens each message refused (the first words of each)

then the mean ratio jitdyn / bare.

    python -m benchmarks.refusals                       # 300 opens at 200 a second, 2 rounds
    python -m benchmarks.refusals --opens 500 --rate 300 --rounds 3

The jitdyn server is `jitdyn serve --processes 1 --tick-budget 0.2` with pendulum_3 sessions held
open in it until admission refuses more: the burst's opens ask for pendulum_3 at 20 Hz, and are
refused at the door (from its price, or with no room for any session) or, priced, on the slow path.
"""

from __future__ import annotations

import argparse
import asyncio
import multiprocessing as mp
import statistics
import time
from collections import Counter
from collections.abc import Iterator
from contextlib import contextmanager

from benchmarks.load import cpu_seconds, local_server

_METHOD = "/jitdyn.v1.DynamicsService/StreamSession"
_CHANNEL = [("grpc.use_local_subchannel_pool", 1)]  # a connection per open


def _open_bytes() -> bytes:
    from jitdyn.v1 import common_pb2, dynamics_pb2

    open_ = dynamics_pb2.OpenSession(model_name="pendulum_3", clock=common_pb2.CLOCK_REALTIME, dt=0.05)
    return dynamics_pb2.StreamSessionRequest(open=open_).SerializeToString()


async def _burst(address: str, opens: int, rate: float, keep: list[object] | None = None) -> Counter[str]:
    """`opens` opens at `rate` a second, each on its own connection; how each ended. With `keep`, the
    opened ones stay open (their channels and calls appended to it)."""
    import grpc

    request, outcomes = _open_bytes(), Counter[str]()

    async def one(i: int) -> None:
        await asyncio.sleep(i / rate)
        channel = grpc.aio.insecure_channel(address, options=_CHANNEL)
        call = channel.stream_stream(_METHOD, request_serializer=None, response_deserializer=None)(
            wait_for_ready=True
        )
        try:
            await call.write(request)
            await call.read()
        except grpc.aio.AioRpcError as error:
            outcomes[f"{error.code().name}: {' '.join((error.details() or '').split()[:24])} ..."] += 1
            await channel.close()
            return
        outcomes["opened"] += 1
        if keep is None:
            await channel.close()
        else:
            keep.extend((channel, call))

    await asyncio.gather(*(one(i) for i in range(opens)))
    return outcomes


def _bare_server(queue: mp.Queue) -> None:  # type: ignore[type-arg]
    import grpc

    async def handler(requests: object, context: grpc.aio.ServicerContext) -> None:  # type: ignore[type-arg]
        async for _ in requests:  # type: ignore[attr-defined]
            await context.abort(grpc.StatusCode.RESOURCE_EXHAUSTED, "full")

    async def main() -> None:
        server = grpc.aio.server()
        handlers = {"StreamSession": grpc.stream_stream_rpc_method_handler(handler)}
        server.add_generic_rpc_handlers(
            (grpc.method_handlers_generic_handler("jitdyn.v1.DynamicsService", handlers),)
        )
        port = server.add_insecure_port("127.0.0.1:0")
        await server.start()
        queue.put(port)
        await server.wait_for_termination()

    asyncio.run(main())


@contextmanager
def _bare() -> Iterator[tuple[str, int]]:
    context = mp.get_context("spawn")
    queue = context.Queue()
    process = context.Process(target=_bare_server, args=(queue,), daemon=True)
    process.start()
    try:
        yield f"127.0.0.1:{queue.get(timeout=60)}", process.pid or 0
    finally:
        process.terminate()
        process.join()


@contextmanager
def _jitdyn() -> Iterator[tuple[str, int]]:
    with local_server(["--processes", "1", "--tick-budget", "0.2"]) as (address, pid):
        yield address, pid


async def _measure(
    address: str, pid: int, opens: int, rate: float, *, hold: bool
) -> tuple[float, float, Counter[str]]:
    """Server and client CPU per open of a burst; with `hold`, first pendulum_3 sessions held open
    until admission refuses more (10 asked for), so that the burst has no room."""
    keep: list[object] = []
    if hold:
        held = await _burst(address, 10, 5, keep)
        if not held["opened"]:
            raise SystemExit(f"refusals.py: the held session did not open: {dict(held)}")
        await asyncio.sleep(1.0)
    try:
        server, client = cpu_seconds(pid), time.process_time()
        outcomes = await _burst(address, opens, rate)
        return (cpu_seconds(pid) - server) / opens, (time.process_time() - client) / opens, outcomes
    finally:
        for item in keep[::2]:
            await item.close()  # type: ignore[attr-defined]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks.refusals",
        description="The server CPU a refused open costs: jitdyn serve against a bare grpc.aio abort, side by side.",
    )
    parser.add_argument("--opens", type=int, default=300, help="opens per burst (default 300)")
    parser.add_argument("--rate", type=float, default=200.0, help="opens a second (default 200)")
    parser.add_argument("--rounds", type=int, default=2, help="rounds, each both servers (default 2)")
    args = parser.parse_args(argv)
    if args.opens < 1 or args.rounds < 1 or not args.rate > 0:
        parser.error(
            f"--opens and --rounds must be >= 1 and --rate > 0, got {args.opens}, {args.rounds}, {args.rate}"
        )
    ratios = []
    for round_ in range(1, args.rounds + 1):
        costs = {}
        for name, start in (("bare grpc.aio", _bare), ("jitdyn serve", _jitdyn)):
            with start() as (address, pid):
                server, client, outcomes = asyncio.run(
                    _measure(address, pid, args.opens, args.rate, hold=start is _jitdyn)
                )
            costs[name] = server
            print(
                f"round {round_}  {name:13s}  server {1e3 * server:5.2f} ms/open  client {1e3 * client:5.2f} ms/open"
            )
            for outcome, count in outcomes.most_common():
                print(f"    {count:4d}  {outcome}")
        ratios.append(costs["jitdyn serve"] / costs["bare grpc.aio"])
        print(f"round {round_}  jitdyn / bare = {ratios[-1]:.2f}")
    print(f"mean jitdyn / bare over {args.rounds} rounds: {statistics.fmean(ratios):.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
