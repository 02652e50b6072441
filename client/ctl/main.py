"""usmswitchctl: the daemon's command line, a thin shell over `usmswitch.client.Client`.

Every command is one or two Client calls plus formatting: human units in ("12ms", "40kHz") and out,
`--json` for the raw result. Exit codes (docs/usmswitchctl.md) are part of the interface:

    0  ok
    1  the daemon refused the call (its error code and message are printed)
    2  usage error: bad command, flag or unit; an export file that cannot be written
    3  cannot reach the daemon: no socket, connection refused or lost, no answer in --timeout
    4  the rig is in FAULT: `status` found FAULT latched, a command was refused with the FAULT
       code, or the stroke `switch` made ended in a stall, driver fault or emergency stop
  141  the reader of our output went away (`usmswitchctl watch | head`), as a shell reports SIGPIPE
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import re
import sys
from collections.abc import Callable
from typing import Any

from usmswitch.protocol.wire import ErrorCode, RpcError

from ..api import find_socket
from ..connection import DEFAULT_TIMEOUT, Client, ConnectionClosed, ReplyTimeout, estop_by_every_path
from .args import (
    EXIT_CONNECT,
    EXIT_FAULT,
    EXIT_INTERRUPTED,
    EXIT_PIPE,
    EXIT_REFUSED,
    EXIT_USAGE,
    PROG,
    UsageError,
)
from .commands import COMMANDS, print_estop
from .exports import cmd_export, cmd_plot
from .from_records import cmd_runs_from, cmd_stats_from, records_source
from .parser import build_parser, check_args


def resolve_address(args: argparse.Namespace) -> str:
    """The address the Client takes: tcp://host:port, the --socket path, or the first socket that exists."""
    if args.tcp is not None:
        return f"tcp://{args.tcp}"  # Client checks host and port and names a bad one
    if args.socket is not None:
        return args.socket
    if args.rig is not None:
        try:
            return str(find_socket(args.rig))
        except ValueError as exc:
            raise UsageError(f"--rig: {exc}") from None
    try:
        return str(find_socket())
    except FileNotFoundError as exc:
        raise ConnectionError(f"{exc} (or give --socket)") from None


def _fail(args: argparse.Namespace, code: int, message: str, rpc_code: int | None = None) -> int:
    if getattr(args, "json", False):
        err: dict[str, Any] = {"exit": code, "message": message}
        if rpc_code is not None:
            err["code"] = rpc_code
            err["name"] = _code_name(rpc_code)
        print(json.dumps({"error": err}, sort_keys=True), file=sys.stderr)
    else:
        print(f"{PROG}: {message}", file=sys.stderr)
    return code


def _no_such_run(args: argparse.Namespace, exc: RpcError, connect: Callable[[], Client]) -> str | None:
    """`--run N` the records lack, refused by the daemon, said as a usage error as a file's is:
    "export: no run 999 in /var/lib/usmswitch/records.sqlite (runs are 1..2)"; None for any other."""
    run = getattr(args, "run", None)
    found = re.search(rf"\bno run {run}\b(?: \((.*)\))?$", exc.message) if run is not None else None
    if exc.code != ErrorCode.INVALID_PARAMS or found is None:
        return None
    where = "the daemon's records"
    with contextlib.suppress(OSError, RpcError, UsageError, ConnectionError), connect() as client:
        where = client.status()["records"].get("path") or where
    return f"{args.command}: no run {run} in {where}" + (f" ({found.group(1)})" if found.group(1) else "")


def _code_name(code: int) -> str:
    try:
        return ErrorCode(code).name
    except ValueError:
        return "UNKNOWN"


def main(argv: list[str] | None = None) -> int:
    """Entry point of `usmswitchctl`."""
    parser = build_parser()
    args = parser.parse_args(argv)
    # SIGPIPE stays ignored (Python's default): a daemon closing the socket under a send must be an
    # error we handle (an estop tries its next path), never a silent kill. A closed stdout
    # (`usmswitchctl watch | head`) is a BrokenPipeError, ended quietly below.
    address = "the daemon"
    try:
        check_args(args)
        timeout = args.timeout / 1e9 if args.timeout is not None else DEFAULT_TIMEOUT

        def connect() -> Client:
            nonlocal address
            address = resolve_address(args)  # only when needed: export from the file has no socket
            try:
                return Client(address, timeout=timeout, token=args.token)
            except ValueError as exc:  # a malformed address, a TCP connection without a token
                raise UsageError(str(exc)) from None

        if args.command in ("runs", "stats") and records_source(args) is not None:
            return (cmd_runs_from if args.command == "runs" else cmd_stats_from)(args)
        if args.command == "export":
            return cmd_export(args, connect)
        if args.command == "plot":
            return cmd_plot(args, connect)
        if args.command == "estop":
            # No connection beforehand: the estop socket, then the main one, each fresh.
            address = resolve_address(args)
            try:
                return print_estop(
                    estop_by_every_path(address, timeout=timeout, token=args.token, by=PROG), args
                )
            except ValueError as exc:
                raise UsageError(str(exc)) from None
        with connect() as client:
            return COMMANDS[args.command](client, args)
    except UsageError as exc:
        return _fail(args, EXIT_USAGE, str(exc))
    except RpcError as exc:
        missing = _no_such_run(args, exc, connect)
        if missing is not None:
            return _fail(args, EXIT_USAGE, missing)
        exit_code = EXIT_FAULT if exc.code == ErrorCode.FAULT else EXIT_REFUSED
        return _fail(args, exit_code, f"refused: [{exc.code} {_code_name(exc.code)}] {exc.message}", exc.code)
    except ReplyTimeout as exc:  # which call, how long, and whether the daemon still answers
        return _fail(args, EXIT_CONNECT, f"timed out: {exc}")
    except TimeoutError as exc:
        return _fail(args, EXIT_CONNECT, f"no answer from the daemon: {exc}")
    except ConnectionClosed as exc:
        return _fail(args, EXIT_CONNECT, f"lost the daemon: {exc}", exc.code)
    except BrokenPipeError:  # our stdout's reader went away: nothing more to say to anyone
        with contextlib.suppress(OSError):
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # the exit's flush
        return EXIT_PIPE
    except OSError as exc:  # no socket file, refused, permission denied, unreachable host
        return _fail(args, EXIT_CONNECT, f"cannot connect to {address}: {exc.strerror or exc}")
    except KeyboardInterrupt:
        return _fail(args, EXIT_INTERRUPTED, "interrupted")


if __name__ == "__main__":
    sys.exit(main())
