#!/usr/bin/env python3
"""Sweep the target T over three values; per target, that run's own strokes and statistics.

python examples/sweep_targets.py            # the local daemon, e.g. `make run`
USMSWITCH_SOCKET=/run/usmswitch/usmswitchd.sock python examples/sweep_targets.py
"""

from usmswitch.client import Client
from usmswitch.protocol.units import format_ns

with Client() as rig:  # found as usmswitchctl finds it
    if rig.status()["state"] == "cycling":
        rig.stop_cycling()  # the sim cycles on its own at start; the sweep wants the rig
    for target in ("12ms", "13ms", "14ms"):
        with rig.run(count=100, period="30ms", target=target) as run:  # Ctrl-C in here stops the rig
            worst = max(abs(rec["error_ns"]) for rec in run)  # this run's strokes, then the loop ends
        stats = run.stats()["all"]
        print(
            f"T = {target}: run {run.run_id}, {stats['strokes']} strokes, "
            f"error std {format_ns(round(stats['error_std_ns']))}, max |error| {format_ns(worst)}"
        )
