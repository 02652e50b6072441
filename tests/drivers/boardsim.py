"""A simulated USM drive board: a real pymodbus server (TCP or RTU) on the documented register map.

The board's state lives in `BoardState`; pymodbus' SimDevice action hook keeps the measured input
registers in step with the written setpoints, and `hang` makes the board stop answering.
"""

from __future__ import annotations

import asyncio
import os
import socket
import threading
import tty
from dataclasses import dataclass

from pymodbus.server import ModbusSerialServer, ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice


@dataclass
class BoardState:
    frequency_hz: int = 40_000
    voltage_vpp: int = 500
    enabled: int = 0
    temperature_c: float = 25.0
    hang: bool = False
    delay_next_s: float = 0.0  # the next request is answered this late (once)
    clamp_frequency_hz: int | None = None  # a board that takes only up to this frequency
    status_bits: int = 0  # OR-ed into the status register (0x04 OVERTEMP, 0x08 OVERCURRENT, 0x10 FAULT)
    raw_inputs: list[int] | None = None  # a broken board: these four input registers, as they are
    writes: int = 0
    reads: int = 0


def _device(state: BoardState, unit: int) -> SimDevice:
    async def action(fc: int, start: int, address: int, count: int, regs: list[int], values: object) -> None:
        if state.hang:
            await asyncio.sleep(2.0)  # longer than any client timeout in the tests
        if state.delay_next_s:
            delay, state.delay_next_s = state.delay_next_s, 0.0
            await asyncio.sleep(delay)
        if fc in (6, 16) and isinstance(values, list):
            for i, v in enumerate(values):
                a = address + i
                if a == 0:
                    clamp = state.clamp_frequency_hz
                    state.frequency_hz = int(v) if clamp is None else min(int(v), clamp)
                    values[i] = state.frequency_hz  # what the board stores
                elif a == 1:
                    state.voltage_vpp = int(v)
                elif a == 2:
                    state.enabled = int(v)
            state.writes += 1
        elif fc == 4:
            state.reads += 1
            regs[0] = round(state.temperature_c * 100) & 0xFFFF
            regs[1] = 0x01 if state.enabled else 0
            regs[2] = state.frequency_hz if state.enabled else 0
            regs[3] = state.voltage_vpp if state.enabled else 0
            regs[1] |= state.status_bits
            if state.raw_inputs is not None:
                regs[: len(state.raw_inputs)] = state.raw_inputs
        return None

    bits = [SimData(0, count=16, values=False, datatype=DataType.BITS)]
    return SimDevice(
        id=unit,
        simdata=(
            bits,
            list(bits),
            [SimData(0, values=[state.frequency_hz, state.voltage_vpp, 0, 0], datatype=DataType.REGISTERS)],
            [SimData(0, values=[2500, 0, 0, 0], datatype=DataType.REGISTERS)],
        ),
        action=action,
    )


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class BoardServer:
    """Run a pymodbus server for the board in a thread with its own event loop."""

    def __init__(self, kind: str, *, unit: int = 1, port: int | None = None, path: str = "") -> None:
        self.state = BoardState()
        self.kind = kind
        self.port = port or free_port()
        self.path = path
        self.unit = unit
        self._loop = asyncio.new_event_loop()
        self._server: ModbusTcpServer | ModbusSerialServer | None = None
        self._thread = threading.Thread(target=self._loop.run_forever, daemon=True)

    def start(self) -> BoardServer:
        self._thread.start()
        dev = _device(self.state, self.unit)

        async def go() -> None:
            if self.kind == "tcp":
                self._server = ModbusTcpServer(dev, address=("127.0.0.1", self.port))
            else:
                self._server = ModbusSerialServer(dev, port=self.path, baudrate=19200, timeout=0.05)
            await self._server.serve_forever(background=True)

        asyncio.run_coroutine_threadsafe(go(), self._loop).result(5)
        return self

    def stop(self) -> None:
        if not self._thread.is_alive():
            return
        if self._server is not None:
            asyncio.run_coroutine_threadsafe(self._server.shutdown(), self._loop).result(5)
            self._server = None

        async def cancel_rest() -> None:
            me = asyncio.current_task()
            rest = [t for t in asyncio.all_tasks() if t is not me]
            for t in rest:
                t.cancel()
            await asyncio.gather(*rest, return_exceptions=True)

        asyncio.run_coroutine_threadsafe(cancel_rest(), self._loop).result(5)
        self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join(5)


class PtyBridge:
    """Two pty pairs joined master to master: a null-modem cable with a device path at each end."""

    def __init__(self) -> None:
        self._a_master, a_slave = os.openpty()
        self._b_master, b_slave = os.openpty()
        for fd in (a_slave, b_slave):
            tty.setraw(fd)
        self._slaves = (a_slave, b_slave)
        self.a = os.ttyname(a_slave)
        self.b = os.ttyname(b_slave)
        self._stop = False
        self._thread = threading.Thread(target=self._pump, daemon=True)
        self._thread.start()

    def _pump(self) -> None:
        import select

        pairs = {self._a_master: self._b_master, self._b_master: self._a_master}
        while not self._stop:
            ready, _, _ = select.select(list(pairs), [], [], 0.05)
            for fd in ready:
                try:
                    data = os.read(fd, 4096)
                except OSError:
                    continue
                os.write(pairs[fd], data)

    def close(self) -> None:
        self._stop = True
        self._thread.join(2)
        for fd in (self._a_master, self._b_master, *self._slaves):
            os.close(fd)
