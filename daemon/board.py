"""The USM drive board beside the loop: set at start and on request, polled on a thread of its own.

Modbus requests take milliseconds (and a timeout when the board is gone), so none of them runs on the
loop thread: the poller keeps the latest `Conditions` for the stroke records (a plain attribute
read for the loop) and turns failures into logged faults, never into a crash.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from concurrent.futures import Future
from typing import Any

import structlog

from usmswitch.drivers import Conditions
from usmswitch.drivers.modbus_board import BoardError, ModbusBoard, RegisterMap
from usmswitch.runtime.realtime import drop_realtime

from .config import ModbusConfig


def board_spec(cfg: ModbusConfig) -> str:
    """The driver's spec string from [modbus] url, unit, timeout and (RTU only) parity."""
    spec = f"{cfg.url}?unit={cfg.unit}&timeout_ms={cfg.timeout_ns // 1_000_000}"
    return spec + f"&parity={cfg.parity}" if cfg.url.startswith("rtu:") else spec


class BoardPoller:
    """Owns a ModbusBoard: configure, poll conditions every interval, apply set_drive requests."""

    def __init__(
        self,
        cfg: ModbusConfig,
        *,
        on_event: Callable[[str, dict[str, Any]], None] | None = None,
        on_fault: Callable[[str], None] | None = None,
        board: ModbusBoard | None = None,
    ) -> None:
        self.cfg = cfg
        self.board = board or ModbusBoard(board_spec(cfg), registers=RegisterMap.from_dict(cfg.registers))
        self.on_event = on_event
        #: Called (from the poller thread) when the board reports a fault bit: drive off, FAULT.
        self.on_fault = on_fault
        self.log = structlog.get_logger("usmswitch.board").bind(board=self.board.describe())
        #: The last conditions read (None until the first good poll, and after a failed one).
        self.latest: Conditions | None = None
        self.frequency_hz = cfg.frequency_hz
        self.voltage_vpp = cfg.voltage_vpp
        self.enabled = True
        self._requests: list[tuple[dict[str, Any], Future[dict[str, Any]]]] = []
        self._wake = threading.Condition()
        self._stop = False
        self._thread: threading.Thread | None = None
        self._was_ok = True

    def start(self) -> None:
        """Connect and set the configured excitation; a board that does not answer is a logged fault."""
        try:
            self.board.open()
            self.board.configure(self.frequency_hz, self.voltage_vpp, enable=True)
            self.log.info("drive board set", frequency_hz=self.frequency_hz, voltage_vpp=self.voltage_vpp)
        except BoardError as exc:
            self._fault(str(exc))
        self._thread = threading.Thread(target=self._run, name="drive-board", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Stop polling and release the board (the drive enable is left to the MCU's own stop)."""
        with self._wake:
            self._stop = True
            self._wake.notify()
        if self._thread is not None:
            self._thread.join(5)
        self.board.close()

    def set_drive(self, **settings: Any) -> Future[dict[str, Any]]:
        """Queue new frequency/voltage/enable settings; the future carries what the board took."""
        fut: Future[dict[str, Any]] = Future()
        with self._wake:
            self._requests.append((settings, fut))
            self._wake.notify()
        return fut

    # -- the poller thread -----------------------------------------------------------------------
    def _run(self) -> None:
        drop_realtime()  # inherited from the loop thread if it was made real-time first
        interval_s = self.cfg.poll_interval_ns / 1e9
        while True:
            with self._wake:
                if not self._requests and not self._stop:
                    self._wake.wait(interval_s)
                if self._stop:
                    return
                requests, self._requests = self._requests, []
            for settings, fut in requests:
                self._apply(settings, fut)
            self._poll()

    def _apply(self, settings: dict[str, Any], fut: Future[dict[str, Any]]) -> None:
        if not fut.set_running_or_notify_cancel():
            return
        try:
            if "frequency_hz" in settings:
                self.board.set_frequency(float(settings["frequency_hz"]))
                self.frequency_hz = float(settings["frequency_hz"])
            if "voltage_vpp" in settings:
                self.board.set_voltage(float(settings["voltage_vpp"]))
                self.voltage_vpp = float(settings["voltage_vpp"])
            if "enabled" in settings:
                self.board.set_enabled(bool(settings["enabled"]))
                self.enabled = bool(settings["enabled"])
        except (BoardError, ValueError) as exc:
            fut.set_exception(exc)
            return
        applied = {
            "frequency_hz": self.frequency_hz,
            "voltage_vpp": self.voltage_vpp,
            "enabled": self.enabled,
        }
        self.log.info("drive board set", **applied)
        fut.set_result(applied)

    def _poll(self) -> None:
        self.latest = self.board.conditions()
        for ev in self.board.take_events():
            self._fault(ev.detail)
        for why in self.board.take_status_faults():
            if self.on_fault is not None:
                self.on_fault(why)
        if self.latest is not None and not self._was_ok:
            self._was_ok = True
            self.log.info("drive board answers again")
            if self.on_event is not None:
                self.on_event("board", {"state": "ok"})

    def _fault(self, detail: str) -> None:
        if self._was_ok:
            self._was_ok = False
            self.log.error("drive board fault", error=detail)
            if self.on_event is not None:
                self.on_event("board", {"state": "fault", "error": detail})
