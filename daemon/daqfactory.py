"""Pick and build the DAQ driver a configuration names (sim, serial MCU, USB MCU)."""

from __future__ import annotations

import secrets

from usmswitch.drivers import Daq

from .config import Config, ConfigError

DRIVER_KINDS = ("sim", "serial", "usb")


def make_daq(config: Config) -> Daq:
    """The driver of `config.driver.kind`, not yet opened."""
    kind = config.driver.kind
    debounce = config.driver.debounce_ns
    if kind == "sim":
        from usmswitch.sim import SimDaq

        seed = config.sim.seed
        if seed is None:  # a new rig each start, unless asked to replay one
            seed = secrets.randbelow(2**63)
        return SimDaq(
            realtime=config.sim.clock == "real",
            seed=seed,
            faults=dict(config.sim.faults),
            debounce_ns=debounce,
        )
    # A hardware-timed device must delay a start by up to the longest target (T_d = T - t_hat <= T).
    c = config.control
    longest_delay = max(c.target_on_ns, c.target_off_ns, c.open_delay_ns)
    if kind == "serial":
        from usmswitch.drivers.serial_mcu import SerialMcuDaq

        s = config.driver.serial
        return SerialMcuDaq(
            s.port,
            s.baudrate,
            debounce_ns=debounce,
            stroke_timeout_ns=config.control.stroke_timeout_ns,
            max_delay_ns=longest_delay,
            reply_timeout_ns=config.driver.reply_timeout_ns,
        )
    if kind == "usb":
        from usmswitch.drivers.usb_mcu import UsbMcuDaq

        u = config.driver.usb
        spec = f"{u.vid:04x}:{u.pid:04x}" + (f":{u.serial}" if u.serial else "")
        return UsbMcuDaq.from_spec(
            spec,
            debounce_ns=debounce,
            stroke_timeout_ns=config.control.stroke_timeout_ns,
            max_delay_ns=longest_delay,
            reply_timeout_ns=config.driver.reply_timeout_ns,
        )
    raise ConfigError("driver.kind", f"unknown driver {kind!r}; known: {', '.join(DRIVER_KINDS)}")
