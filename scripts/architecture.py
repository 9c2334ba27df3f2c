"""Draws docs/img/architecture.png, the picture of jitdyn across machines in docs/scale.md.

python scripts/architecture.py [--out docs/img/architecture.png]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
from matplotlib.patches import FancyArrowPatch, FancyBboxPatch

_INK = "#222222"
_CLIENT = "#dbe9f6"
_EDGE = "#fde2c8"
_REPLICA = "#d9f0d3"
_SHARED = "#e8ddf3"
_DOWN = "#f4cccc"


def _box(
    ax: plt.Axes, x: float, y: float, w: float, h: float, colour: str, title: str, body: str = ""
) -> None:
    ax.add_patch(
        FancyBboxPatch((x, y), w, h, boxstyle="round,pad=0.02,rounding_size=0.08", fc=colour, ec=_INK, lw=1.2)
    )
    ax.text(x + w / 2, y + h - 0.17, title, ha="center", va="top", fontsize=10.5, weight="bold", color=_INK)
    if body:
        ax.text(
            x + w / 2, y + h - 0.52, body, ha="center", va="top", fontsize=8.2, color=_INK, linespacing=1.35
        )


def _arrow(
    ax: plt.Axes, start: tuple[float, float], end: tuple[float, float], label: str = "", **style: object
) -> None:
    ax.add_patch(
        FancyArrowPatch(start, end, arrowstyle="-|>", mutation_scale=13, lw=1.3, color=_INK, **style)  # type: ignore[arg-type]
    )
    if label:
        mx, my = (start[0] + end[0]) / 2, (start[1] + end[1]) / 2
        ax.text(
            mx,
            my,
            label,
            ha="center",
            va="center",
            fontsize=7.8,
            color=_INK,
            bbox={"fc": "white", "ec": "none", "pad": 1.2},
        )


def draw(out: Path) -> None:
    fig, ax = plt.subplots(figsize=(12, 7.2))
    ax.set_xlim(0, 12)
    ax.set_ylim(0, 7.2)
    ax.axis("off")

    # Clients.
    for i, (name, what) in enumerate(
        [
            ("prosthesis", "SDK, REALTIME 100 Hz"),
            ("lab experiment", "SDK, LOCKSTEP"),
            ("simulation", "any language (proto/)"),
        ]
    ):
        _box(
            ax,
            0.2,
            5.2 - 1.75 * i,
            2.2,
            1.35,
            _CLIENT,
            name,
            what + "\nresumes by itself\non UNAVAILABLE / moving",
        )
    # Balancer.
    _box(
        ax,
        3.2,
        2.6,
        2.0,
        2.4,
        _EDGE,
        "gRPC balancer",
        "HAProxy (deploy/haproxy)\nh2 both sides, round robin\nhealth: raw gRPC\nHealth/Check frames\n"
        "or a K8s Service /\nclient round_robin",
    )
    for i in range(3):
        _arrow(ax, (2.4, 5.85 - 1.75 * i), (3.2, 3.8))
    ax.text(4.2, 5.15, "one address", fontsize=8, ha="center", color=_INK)
    # Replicas.
    names = ["replica A  (127.0.0.2)", "replica B  (127.0.0.3)", "replica C  (killed)"]
    colours = [_REPLICA, _REPLICA, _DOWN]
    bodies = [
        "jitdyn serve: MuJoCo + UKF\nlocal folder: model cache,\nParquet before publishing",
        "jitdyn serve: MuJoCo + UKF\nlocal folder: model cache,\nParquet before publishing",
        "health check fails: the\nbalancer stops sending to it;\nits lease expires",
    ]
    for i in range(3):
        y = 5.3 - 2.05 * i
        _box(ax, 6.0, y, 2.6, 1.7, colours[i], names[i], bodies[i])
        if i < 2:
            _arrow(ax, (5.2, 3.8), (6.0, y + 0.85), "bidi stream" if i == 0 else "")
    ax.plot([5.2, 6.0], [3.6, 1.6], ls=":", color=_INK, lw=1.2)
    ax.text(5.6, 2.45, "x", fontsize=14, ha="center", va="center", color="#b00000", weight="bold")
    _arrow(ax, (7.3, 2.9), (7.3, 3.25), "", linestyle="dashed")
    ax.text(
        7.3,
        3.08,
        "its sessions resume on B (SDK, token)",
        fontsize=7.8,
        ha="center",
        va="center",
        color=_INK,
        bbox={"fc": "white", "ec": "none", "pad": 1.0},
    )
    # Shared tier.
    _box(
        ax,
        9.4,
        4.0,
        2.4,
        2.6,
        _SHARED,
        "PostgreSQL",
        "session index (SQL)\nmodel_blobs (registry)\nsession_leases: owner,\nepoch (fencing)\n"
        "session_log: frames per\ncommit window = durable",
    )
    _box(
        ax,
        9.4,
        0.5,
        2.4,
        2.6,
        _SHARED,
        "data root",
        "s3://bucket/prefix or a\nshared folder (pyarrow.fs)\nframes/model=/date=/\n<session>.parquet\n"
        "DuckDB / pyarrow read it",
    )
    for i in range(2):
        y = 5.3 - 2.05 * i
        _arrow(ax, (8.6, y + 1.2), (9.4, 5.6 - 0.5 * i), "window commits" if i == 0 else "")
        _arrow(ax, (8.6, y + 0.4), (9.4, 2.4 - 0.5 * i), "Parquet at close" if i == 1 else "")
    ax.text(
        6.0,
        0.15,
        "A kill -9 loses no acknowledged frame: durable_seq counts a frame only once its window is in "
        "PostgreSQL.",
        fontsize=8.5,
        color=_INK,
    )
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    plt.close(fig)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("docs/img/architecture.png"))
    draw(parser.parse_args().out)


if __name__ == "__main__":
    main()
