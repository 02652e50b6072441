"""Run the benchmarks: every benchmarks/bench_*.py module's main(), or those named on the command line."""

from __future__ import annotations

import importlib
import pkgutil
import sys
import time

import benchmarks


def main(argv: list[str]) -> int:
    modules = pkgutil.iter_modules(benchmarks.__path__)
    names = sorted(m.name[len("bench_") :] for m in modules if m.name.startswith("bench_"))
    wanted = argv or names
    unknown = [w for w in wanted if w not in names]
    if unknown:
        print(f"unknown benchmark(s): {', '.join(unknown)}; have: {', '.join(names)}", file=sys.stderr)
        return 2
    failed = 0
    for name in wanted:
        print(f"\n=== {name} ===", flush=True)
        t0 = time.perf_counter()
        mod = importlib.import_module(f"benchmarks.bench_{name}")
        rc = mod.main() or 0
        failed += rc != 0
        print(f"({name}: {time.perf_counter() - t0:.1f} s{', TARGET MISSED' if rc else ''})", flush=True)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
