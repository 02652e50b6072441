"""usmswitchd: the control daemon's command line."""

from __future__ import annotations

import sys


def main(argv: list[str] | None = None) -> int:
    """Entry point of `usmswitchd`."""
    print("usmswitchd: not yet: the control loop lands with the daemon issue", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
