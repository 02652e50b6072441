"""The MCU emulator behind a pty pair: the slave's path is the serial port the `serial` driver opens."""

from __future__ import annotations

import contextlib
import os
import select
import threading
import tty
from pathlib import Path

from .mcu_firmware import McuEmulator


class PtyLink:
    """The emulator behind a pty pair: the slave's path, via a stable symlink, is the serial port.

    `unplug()` closes the pty (the host's reads fail with EIO, as on a USB-serial unplug) and
    removes the symlink; `replug()` makes a new pty and points the symlink at it, as udev does for
    /dev/serial/by-id.
    """

    def __init__(self, emulator: McuEmulator, link_path: str | os.PathLike[str]) -> None:
        self.emulator = emulator
        self.link_path = Path(link_path)
        self._master = -1
        self._slave = -1
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self.plugged = False
        self.bytes_in = 0

    @property
    def slave_path(self) -> str:
        """The current pty slave device."""
        return os.ttyname(self._slave)

    def plug(self) -> PtyLink:
        """Create the pty, point the symlink at it, start pumping bytes."""
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)
        tty.setraw(self._master)
        tmp = self.link_path.with_name(self.link_path.name + ".new")
        tmp.unlink(missing_ok=True)
        tmp.symlink_to(os.ttyname(self._slave))
        tmp.replace(self.link_path)
        self._stop.clear()
        self._thread = threading.Thread(target=self._pump, args=(self._master,), name="pty-link", daemon=True)
        self._thread.start()
        master = self._master
        self.emulator.attach(lambda data: _write_all(master, data))
        self.plugged = True
        return self

    def _pump(self, fd: int) -> None:
        while not self._stop.is_set():
            try:
                ready, _, _ = select.select([fd], [], [], 0.05)
                if not ready:
                    continue
                data = os.read(fd, 4096)
            except OSError:
                return  # closed by unplug, or the slave side hung up for good
            if data:
                self.bytes_in += len(data)
                self.emulator.receive(data)

    def unplug(self) -> None:
        """Pull the cable: the pty goes away and so does the symlink."""
        if not self.plugged:
            return
        self.plugged = False
        self.emulator.detach()
        self._stop.set()
        if self._thread is not None:
            self._thread.join(2)
        for fd in (self._master, self._slave):
            with contextlib.suppress(OSError):
                os.close(fd)
        self._master = self._slave = -1
        self.link_path.unlink(missing_ok=True)

    def replug(self, *, power_cycle: bool = True) -> None:
        """Plug back in (a bus-powered MCU reboots: clock and session restart)."""
        if power_cycle:
            self.emulator.power_cycle()
        self.plug()

    def close(self) -> None:
        """Unplug for good."""
        self.unplug()


def _write_all(fd: int, data: bytes) -> None:
    view = memoryview(data)
    while view:
        n = os.write(fd, view)
        view = view[n:]
