"""usmswitchd: the control daemon's command line (a thin shell over daemon.service)."""

from __future__ import annotations

import argparse
import faulthandler
import json
import os
import sys

# Before numpy loads (the simulated rig's model): OpenBLAS would start a worker thread per core at
# normal priority that the daemon never uses (no matrix work here), and at exit the kernel has to
# schedule each one to end it: 30 ms and more on a busy machine, inside the SIGTERM-to-exit bound.
# Inherited by the server process. A user's own setting wins.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from usmswitch.predictor import DEFAULT_MODEL, MODELS
from usmswitch.protocol.version import version_text
from usmswitch.protocol.wire import PROTOCOL_VERSION
from usmswitch.runtime.process_exit import exit_now

from .config import Config, ConfigError, load_config

EXIT_CONFIG = 2  # a bad config or flag: nothing was started
# A part could not start: driver missing, socket in use, state dir unwritable or in use by another
# daemon (the message names the directory and the pid holding it), socket directory not private.
EXIT_START = 3
# 4: the daemon ran and stopped, but records were left unwritten, dropped or rejected
# (service.EXIT_RECORDS_LOST, returned by Daemon.run).


def build_parser() -> argparse.ArgumentParser:
    """The flags; each overrides the config file key named in its help."""
    p = argparse.ArgumentParser(
        prog="usmswitchd",
        description="USM switch controller: delays each motor start by T - t_hat so every stroke "
        "ends T after its command. With no config it runs the simulated rig.",
    )
    p.add_argument("--version", action="version", version=version_text("usmswitchd", PROTOCOL_VERSION))
    p.add_argument("--config", help="TOML config file (docs/config.md)")
    p.add_argument("--sim", action="store_true", default=None, help="run on the simulated rig (driver.kind)")
    p.add_argument("--driver", choices=("sim", "serial", "usb"), help="driver.kind")
    p.add_argument("--port", help="driver.serial.port, e.g. /dev/usmswitch")
    p.add_argument(
        "--baudrate", type=int, help="driver.serial.baudrate (default 1000000, the reference firmware's)"
    )
    p.add_argument("--socket", help="socket.path (Unix socket for lab scripts)")
    p.add_argument("--tcp", help="socket.tcp, e.g. 127.0.0.1:7770 (needs socket.tcp_token in the file)")
    p.add_argument("--state-dir", help="daemon.state_dir (records.sqlite lives there)")
    p.add_argument("--rig", help="daemon.rig: this rig's name, stamped on every record (usmswitchd@RIG)")
    p.add_argument("--log-format", choices=("json", "console", "auto"), help="daemon.log_format")
    p.add_argument("--log-level", choices=("debug", "info", "warning", "error"), help="daemon.log_level")
    p.add_argument("--target", help="control.target for both directions, e.g. 12ms")
    p.add_argument("--mode", choices=("closed", "open"), help="control.mode")
    p.add_argument("--model", choices=MODELS, help=f"control.model (else {DEFAULT_MODEL})")
    p.add_argument("--order", help="control.order: 1..8 or auto")
    p.add_argument("--window", type=int, help="control.window (strokes)")
    p.add_argument("--period", help="cycle.period, e.g. 50ms")
    p.add_argument("--count", type=int, help="cycle.count (0 = until stopped)")
    auto = p.add_mutually_exclusive_group()
    auto.add_argument(
        "--autostart", dest="autostart", action="store_true", default=None, help="cycle at start"
    )
    auto.add_argument("--no-autostart", dest="autostart", action="store_false", help="start idle")
    p.add_argument("--seed", type=int, help="sim.seed")
    p.add_argument("--sim-clock", choices=("real", "virtual"), help="sim.clock")
    p.add_argument(
        "--priority",
        help='realtime.sched_fifo_priority: "auto" (default: 50 where permitted), 0 (off) or 1..99',
    )
    p.add_argument(
        "--postgres",
        metavar="URL",
        help="records.postgres_url: also ship the records to this database (postgresql://...)",
    )
    p.add_argument(
        "--metrics",
        metavar="HOST:PORT",
        help="metrics.listen: serve the Prometheus page (a bare port: loopback)",
    )
    p.add_argument(
        "--web",
        metavar="[HOST:]PORT",
        help="web.listen: serve the browser panel (a bare port: loopback); docs/panel.md",
    )
    p.add_argument(
        "--check-config", action="store_true", help="validate, print the merged config as JSON, exit"
    )
    return p


def main(argv: list[str] | None = None) -> int:
    """Entry point of `usmswitchd`."""
    args = build_parser().parse_args(argv)
    overrides = {k: v for k, v in vars(args).items() if k not in ("config", "check_config")}
    if overrides.get("order") not in (None, "auto"):
        try:
            overrides["order"] = int(overrides["order"])
        except ValueError:
            print(f"usmswitchd: --order: expected 1..8 or auto, got {overrides['order']!r}", file=sys.stderr)
            return EXIT_CONFIG
    try:
        config = load_config(args.config, overrides)
    except ConfigError as exc:
        print(f"usmswitchd: config error: {exc}", file=sys.stderr)
        return EXIT_CONFIG
    if args.check_config:
        try:
            check_reach_at_start(config)
        except ConfigError as exc:
            print(f"usmswitchd: config error: {exc}", file=sys.stderr)
            return EXIT_CONFIG
        print(json.dumps(config.to_dict(redact=True), indent=2, default=str))
        return 0
    from .service import Daemon

    daemon = Daemon(config)
    try:
        daemon.start()
    except ConfigError as exc:  # found only once the rig is known (a target it cannot reach)
        daemon.log.error("config error", error=str(exc))
        daemon.stop()
        print(f"usmswitchd: config error: {exc}", file=sys.stderr)
        return EXIT_CONFIG
    except Exception as exc:
        daemon.log.error("start-up failed", error=f"{type(exc).__name__}: {exc}")
        daemon.stop()
        return EXIT_START
    return daemon.run()


def check_reach_at_start(config: Config) -> None:
    """The start-up's refusal of a closed-loop target below what the rig reaches, as far as the
    config knows the rig: each direction's first prediction from its `nominal` or, on the simulated
    rig, the rig's model (records in the state directory, which the daemon warm-starts from, may
    know it better: it checks again at start). Nothing is known on hardware without a nominal: the
    first strokes commission it."""
    from . import reach
    from .daqfactory import make_daq
    from .service import direction_predictors, first_guesses

    if config.control.mode != "closed":
        return
    rig = make_daq(config) if config.driver.kind == "sim" else None
    nominals, sources = first_guesses(config, rig if rig is not None else _UnknownRig())
    if all(source == "guess" for source in sources):
        return
    c = config.control
    try:
        reach.check_reach(
            direction_predictors(config, None, nominals), (c.target_on_ns, c.target_off_ns), c.late_margin_ns
        )
    except reach.TargetUnreachableError as exc:
        raise ConfigError("control.target", reach.without_allow_late(str(exc))) from None


class _UnknownRig:
    """A rig the config says nothing of: no model of its stroke."""

    def expected_stroke_ns(self, direction: object) -> None:
        return None


def entry() -> None:
    """The `usmswitchd` command: main(), then out without the interpreter's teardown (once main()
    returns, the drive is off, every record is committed, the children are gone and the state
    directory unlocked: Daemon.stop)."""
    # A daemon that hangs shows where: systemd's watchdog ends it with SIGABRT, and every thread's
    # stack goes to stderr (the journal) before it dies.
    faulthandler.enable(all_threads=True)
    exit_now(main())


if __name__ == "__main__":
    entry()
