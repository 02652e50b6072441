"""The firmware's worst stack depth, from its image: avr-gcc's -fstack-usage frames along the
deepest call chain from main (calls read from the disassembly), plus the interrupts that can nest
on top of it: each handler that re-enables interrupts (a `sei` in it) once, and the deepest of the
others. A frame counts its return address (3 bytes on the ATmega2560). The hand-written handlers
in vectors.S push their own bytes, counted here.

    python3 stack_depth.py ELF SU [OBJDUMP]   ->  prints "N" (bytes), and the chain on stderr
"""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

# vectors.S: (bytes pushed, including the 3-byte return address; the function it jumps to).
HAND_WRITTEN = {
    "__vector_5": (4, None),  # INT4: the arrival cut, r24
    "__vector_6": (4, None),  # INT5
    "__vector_41": (4, "__vector_capt4_tail"),  # TIMER4_CAPT stub: r24, popped before its jmp
    "__vector_46": (4, "__vector_capt5_tail"),  # TIMER5_CAPT stub
    "__vector_45": (5, None),  # TIMER4_OVF (the plant image's clock)
    "__vector_50": (5, None),  # TIMER5_OVF (the clock)
    "__vector_47": (3, None),  # TIMER5_COMPA: reti
    "__vector_25": (8, None),  # USART0_RX: r24, SREG, r25, r30, r31 (interrupts on again: nests)
    "__vector_26": (8, None),  # USART0_UDRE: the same
}
FUNC = re.compile(r"^[0-9a-f]+ <(?P<name>[^>]+)>:$")
CALL = re.compile(r"\s(?:call|rcall|jmp|rjmp)\s.*<(?P<name>[^>+]+)>")


def main(argv: list[str]) -> int:
    elf, su = argv[1], argv[2]
    objdump = argv[3] if len(argv) > 3 else "avr-objdump"
    frames: dict[str, int] = {}
    for line in Path(su).read_text().splitlines():
        where, size, _ = line.split("\t")
        name = where.rsplit(":", 1)[1]
        frames[name] = max(frames.get(name, 0), int(size))
    calls: dict[str, set[str]] = {}
    seis: set[str] = set()
    cur = None
    for line in subprocess.run(
        [objdump, "-d", elf], capture_output=True, text=True, check=True
    ).stdout.splitlines():
        m = FUNC.match(line)
        if m:
            cur = m["name"]
            calls.setdefault(cur, set())
            continue
        if cur is None:
            continue
        c = CALL.search(line)
        if c and c["name"] != cur:
            calls[cur].add(c["name"])
        if re.search(r"\tsei\b", line):
            seis.add(cur)

    def depth(f: str, seen: tuple[str, ...] = ()) -> tuple[int, list[str]]:
        if f in seen:
            raise SystemExit(f"stack_depth: recursion through {f}: no bound")
        own, tail = HAND_WRITTEN.get(f, (frames.get(f, 0), None))
        best, chain = 0, []
        for g in sorted(calls.get(f, ())):
            if g.startswith("__vector_") and g not in HAND_WRITTEN and f != "__vectors":
                continue
            if g == "__vectors" or g.startswith("__bad_interrupt"):
                continue
            d, ch = depth(g, (*seen, f))
            if d > best:
                best, chain = d, ch
        if tail is not None:
            d, ch = depth(tail, (*seen, f))
            return max(own, d), [f, *ch] if d > own else [f]
        return own + best, [f, *chain]

    main_d, main_chain = depth("main")
    isrs = sorted({f for f in calls if re.fullmatch(r"__vector_\d+", f)} | set(HAND_WRITTEN) & set(calls))

    def nests(f: str) -> bool:  # it, or the tail it jumps to, turns interrupts on again
        return f in seis or HAND_WRITTEN.get(f, (0, None))[1] in seis

    nesting = [f for f in isrs if nests(f)]
    others = [f for f in isrs if not nests(f)]
    nest_d = sum(depth(f)[0] for f in nesting)
    other_d, other_chain = max((depth(f) for f in others), default=(0, []))
    total = main_d + nest_d + other_d
    print(
        f"main {main_d} ({' > '.join(main_chain)}), interrupts re-enabling {'+'.join(nesting) or '-'} "
        f"{nest_d}, then the deepest other {other_d} ({' > '.join(other_chain)})",
        file=sys.stderr,
    )
    print(total)
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv))
