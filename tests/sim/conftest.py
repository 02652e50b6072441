"""Helpers for the simulated rig's tests: drive strokes through SimDaq the way the daemon does."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest

from usmswitch.drivers import Direction, EventKind
from usmswitch.sim import SimDaq

StrokeRun = tuple[list[Direction], list[int]]


def run_strokes(daq: SimDaq, n: int, *, gap_ns: int = 1_000_000, timeout_ns: int = 40_000_000) -> StrokeRun:
    """Alternate on/off strokes, each commanded `gap_ns` after the previous arrival (back-to-back
    reciprocation between the limit sensors, as in Fig. 6); return directions and operating times."""
    dirs: list[Direction] = []
    ops: list[int] = []
    direction = Direction.ON
    for _ in range(n):
        daq.arm(direction, gap_ns)
        cmd = daq.command()
        while True:
            ev = daq.recv(timeout_ns)
            assert ev is not None, f"stroke {len(ops)} ({direction.name}) did not arrive"
            if ev.kind is EventKind.EDGE and ev.channel == direction.dest and ev.level == 1:
                break
        dirs.append(direction)
        ops.append(ev.t_ns - cmd.t_start_ns)
        direction = direction.opposite
    return dirs, ops


def split(run: StrokeRun) -> dict[Direction, np.ndarray]:
    """Operating times per direction, in stroke order."""
    dirs, ops = run
    return {
        d: np.array([t for dd, t in zip(dirs, ops, strict=True) if dd is d], dtype=float) for d in Direction
    }


@pytest.fixture
def strokes() -> Callable[..., StrokeRun]:
    return run_strokes


@pytest.fixture
def per_direction() -> Callable[[StrokeRun], dict[Direction, np.ndarray]]:
    return split
