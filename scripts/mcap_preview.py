"""Draw an MCAP export of `jitdyn sessions export --format mcap` from its own channels, read back
with the mcap reader: what Foxglove would show, for a machine without Foxglove.

    python scripts/mcap_preview.py SESSION.mcap --out docs/img/session_mcap.png

Top: the bodies' origins in the world, chained from /tf's frame transforms (Foxglove's 3D panel,
seen along y), a pose every few tenths of a second, darker later. Below, on the file's time axis:
/jitdyn/source, the joint angles of /jitdyn/joint_states against /jitdyn/frames, the generalized
forces of /jitdyn/forces and the frame delay of /jitdyn/lateness.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections import defaultdict
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from mcap.reader import make_reader

COLORS = {"MEASURED": "tab:blue", "PREDICTED": "tab:orange", "CORRECTED": "tab:green"}


def read(path: Path) -> tuple[dict[str, list[tuple[float, dict[str, Any]]]], dict[str, str]]:
    """Messages by topic as (s since the first message, JSON), and the session's metadata."""
    topics: dict[str, list[tuple[int, dict[str, Any]]]] = defaultdict(list)
    with path.open("rb") as stream:
        reader = make_reader(stream)
        for _, channel, message in reader.iter_messages(log_time_order=True):
            topics[channel.topic].append((message.log_time, json.loads(message.data)))
        metadata = next(r.metadata for r in reader.iter_metadata() if r.name == "jitdyn.session")
    start = min(messages[0][0] for messages in topics.values())
    return {t: [((ns - start) / 1e9, m) for ns, m in ms] for t, ms in topics.items()}, metadata


def _rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """v rotated by the unit quaternion q = (x, y, z, w)."""
    u, w = q[:3], q[3]
    return v + 2.0 * np.cross(u, np.cross(u, v) + w * v)


def _compose(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The quaternion (x, y, z, w) of rotation a then b in a's frame: a * b."""
    (ax, ay, az, aw), (bx, by, bz, bw) = a, b
    return np.array(
        [
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
            aw * bw - ax * bx - ay * by - az * bz,
        ]
    )


def world_origins(message: dict[str, Any]) -> dict[str, np.ndarray]:
    """Each frame's origin in "world", chaining the message's parent-to-child transforms."""
    poses: dict[str, tuple[np.ndarray, np.ndarray]] = {"world": (np.zeros(3), np.array([0.0, 0.0, 0.0, 1.0]))}
    for transform in message["transforms"]:  # parents come before their children
        position, rotation = poses[transform["parent_frame_id"]]
        t = np.array([transform["translation"][k] for k in "xyz"])
        r = np.array([transform["rotation"][k] for k in "xyzw"])
        poses[transform["child_frame_id"]] = (position + _rotate(rotation, t), _compose(rotation, r))
    return {name: position for name, (position, _) in poses.items()}


def _bodies(ax: Any, transforms: list[tuple[float, dict[str, Any]]]) -> None:
    step = max(1, len(transforms) // 12)
    shown = transforms[::step]
    for k, (t, message) in enumerate(shown):
        origins = world_origins(message)
        parents = {tr["child_frame_id"]: tr["parent_frame_id"] for tr in message["transforms"]}
        shade = 0.25 + 0.75 * k / max(1, len(shown) - 1)
        for child, parent in parents.items():
            if parent == "world":
                continue
            a, b = origins[parent], origins[child]
            ax.plot([a[0], b[0]], [a[2], b[2]], color=plt.cm.Blues(shade), lw=2)
        xs = [origins[c][0] for c in parents]
        zs = [origins[c][2] for c in parents]
        ax.plot(
            xs,
            zs,
            "o",
            color=plt.cm.Blues(shade),
            ms=4,
            label=f"t = {t:.1f} s" if k in (0, len(shown) - 1) else None,
        )
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("z (m)")
    ax.set_title("/tf: body origins in the world, chained from the frame transforms (seen along y)")
    ax.legend(loc="upper right", fontsize=8)


def _series(axes: Any, topics: dict[str, list[tuple[float, dict[str, Any]]]]) -> None:
    strip, angles, forces, lateness = axes
    for t, m in topics["/jitdyn/source"]:
        strip.axvline(t, color=COLORS[m["source"]], lw=1.5)
        if m["corrected"]:
            strip.plot(t, 0.5, "|", color=COLORS["CORRECTED"], ms=10, mew=2)
    strip.set_yticks([])
    strip.set_title(
        "/jitdyn/source: the answer when due (blue MEASURED, orange PREDICTED); green ticks: CORRECTED"
    )
    states = topics["/jitdyn/joint_states"]
    names = states[0][1]["qpos"]["name"]
    for j, name in enumerate(names):
        line = angles.plot(
            [t for t, _ in states], [m["qpos"]["value"][j] for _, m in states], label=f"{name} answered"
        )
        frames = topics.get("/jitdyn/frames", [])
        angles.plot(
            [t for t, _ in frames],
            [m["qpos"]["value"][j] for _, m in frames],
            ".",
            ms=3,
            color=line[0].get_color(),
            alpha=0.6,
        )
    angles.set_ylabel("q (rad)")
    angles.set_title("/jitdyn/joint_states (lines) and /jitdyn/frames (dots)")
    angles.legend(loc="upper right", fontsize=8, ncol=len(names))
    pushed = topics["/jitdyn/forces"]
    for j, name in enumerate(pushed[0][1]["qfrc_inverse"]["name"]):
        forces.plot([t for t, _ in pushed], [m["qfrc_inverse"]["value"][j] for _, m in pushed], label=name)
    forces.set_ylabel("qfrc_inverse (N m, N)")
    forces.set_title("/jitdyn/forces: inverse dynamics")
    late = [(t, m["frame_delay"]) for t, m in topics["/jitdyn/lateness"] if m["frame_delay"] is not None]
    lateness.plot([t for t, _ in late], [1e3 * d for _, d in late], ".", ms=4, color="tab:purple")
    lateness.set_ylabel("frame delay (ms)")
    lateness.set_xlabel("time (s, from the session's first tick)")
    lateness.set_title("/jitdyn/lateness: each frame's arrival after its tick's time")


def draw(path: Path, out: Path) -> None:
    topics, metadata = read(path)
    fig = plt.figure(figsize=(11, 12), layout="constrained")
    grid = fig.add_gridspec(5, 1, height_ratios=[3.2, 0.5, 1.6, 1.6, 1.3])
    _bodies(fig.add_subplot(grid[0]), topics["/tf"])
    strip = fig.add_subplot(grid[1])
    rest = [fig.add_subplot(grid[i], sharex=strip) for i in (2, 3, 4)]
    _series([strip, *rest], topics)
    fig.suptitle(
        f"{path.name}: session {metadata['session_id'][:8]}, {metadata['model']}, {metadata['scenario']} "
        f"{metadata['clock']}, drawn from the MCAP's own channels"
    )
    fig.savefig(out, dpi=90)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("mcap", type=Path, help="a file of `jitdyn sessions export --format mcap`")
    parser.add_argument("--out", type=Path, required=True, help="the PNG to write")
    args = parser.parse_args()
    if not args.mcap.is_file():
        parser.error(f"{args.mcap}: no such file")
    draw(args.mcap, args.out)
    print(f"drew {args.mcap} to {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
