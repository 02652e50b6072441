"""The emulator of the rig's microcontroller: its public face and its command line.

The pieces, one job each:

- `mcu_firmware`: `McuEmulator`, the firmware: protocol state machine, device clock, stroke
  timing, watchdog, bootloader, and the wire faults it can be told to inject;
- `mcu_rig`: `Mover`, the bridge to the rig model: position, limit sensors, a stroke's edges;
- `mcu_pty`: `PtyLink`, the emulator behind a pty pair (the `serial` driver's port), unplug and
  replug included;
- `mcu_usb`: `UsbDevice` and `UsbBackend`, the emulator behind a pyusb backend (the `usb` driver).

`python -m usmswitch.sim.mcu_emulator --link PATH` runs it on a pty until SIGTERM or SIGINT;
`--sched-fifo N` runs it at SCHED_FIFO N where the process may (a chip is never descheduled by the
host's other work; a test beside a busy machine wants the same of its stand-in).
"""

from __future__ import annotations

import os
import threading

from .mcu_firmware import (
    ALL_CAPS,
    FW_VERSION,
    MAX_COMMAND_SKEW_US,
    MAX_DELAY_US,
    InjectedFaults,
    McuEmulator,
    UnknownFrame,
)
from .mcu_pty import PtyLink
from .mcu_rig import BOUNCE_NS, Mover, StrokePlan
from .mcu_usb import UsbBackend, UsbDevice

__all__ = [
    "ALL_CAPS",
    "BOUNCE_NS",
    "FW_VERSION",
    "MAX_COMMAND_SKEW_US",
    "MAX_DELAY_US",
    "InjectedFaults",
    "McuEmulator",
    "Mover",
    "PtyLink",
    "StrokePlan",
    "UnknownFrame",
    "UsbBackend",
    "UsbDevice",
    "main",
]


def main(argv: list[str] | None = None) -> int:
    """Run the emulator on a pty until SIGTERM/SIGINT: `python -m usmswitch.sim.mcu_emulator --link PATH`."""
    import argparse
    import signal

    ap = argparse.ArgumentParser(
        description="usmswitch MCU firmware emulator on a pty (serial driver target)"
    )
    ap.add_argument("--link", required=True, help="symlink to create for the pty slave, e.g. /tmp/usmswitch")
    ap.add_argument("--seed", type=int, default=0, help="rig model seed")
    ap.add_argument("--clock-start-us", type=int, default=0, help="device clock at power-on (wrap tests)")
    ap.add_argument("--drift-ppm", type=int, default=0, help="device crystal error")
    ap.add_argument(
        "--sched-fifo",
        type=int,
        default=0,
        metavar="N",
        help="run at SCHED_FIFO priority N (1..99) if permitted, else say so and run as is (0: as is)",
    )
    args = ap.parse_args(argv)
    if not 0 <= args.sched_fifo <= 99:
        ap.error(f"--sched-fifo must be 0..99, got {args.sched_fifo}")
    # Before any thread starts: the emulator's threads inherit the policy of the one creating them.
    scheduling = _sched_fifo(args.sched_fifo)
    emu = McuEmulator(seed=args.seed, clock_start_us=args.clock_start_us, drift_ppm=args.drift_ppm).start()
    link = PtyLink(emu, args.link).plug()
    done = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: done.set())
    print(f"mcu emulator on {link.slave_path} via {args.link}, {scheduling}", flush=True)
    done.wait()
    link.close()
    emu.stop()
    return 0


def _sched_fifo(priority: int) -> str:
    """SCHED_FIFO `priority` for this thread (0: left as is); how it runs, in words."""
    if not priority:
        return "scheduled as started"
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    except OSError as exc:
        return f"SCHED_OTHER (SCHED_FIFO {priority} refused: {exc.strerror})"
    return f"SCHED_FIFO {priority}"


if __name__ == "__main__":
    raise SystemExit(main())
