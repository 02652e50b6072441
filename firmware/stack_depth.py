"""The firmware's worst stack depth, from its image: a true bound, or an error saying why there is none.

avr-gcc's -fstack-usage frames along the deepest call chain from main (calls read from the
disassembly), plus the interrupt handlers that can be on the stack above it at once. A handler
that keeps interrupts off throughout cannot be interrupted, so at most one of those is on top.
A handler that turns them on again (a `sei` in it or in what it calls) must first mask its own
interrupt (SELF_MASKING below, checked in the disassembly: an `andi` clearing the enable bit and
its `sts` to the enable register before the first `sei`) and unmask it only with interrupts off
again: it is then on the stack at most once. The bound is main's chain + each self-masking
handler once + the deepest of the others. A handler that turns interrupts on without masking its
own interrupt could nest in itself without limit: the script stops with no bound (issue 33: the
capture tails did, and a 40 kHz sensor line ran the stack through RAM). A frame counts its return
address (3 bytes on the ATmega2560). The hand-written handlers in vectors.S push their own bytes,
counted here.

    python3 stack_depth.py ELF SU [OBJDUMP]   ->  prints "N" (bytes), and the chain on stderr
"""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

# vectors.S: bytes pushed, including the 3-byte return address (what they call is read from the
# disassembly and added).
HAND_WRITTEN = {
    "__vector_5": 4,  # INT4: the arrival cut, r24
    "__vector_6": 4,  # INT5
    "__vector_41": 19,  # TIMER4_CAPT: r24, SREG, r0, r1, r18-r23, r25-r27, r30, r31, RAMPZ; calls its tail
    "__vector_46": 19,  # TIMER5_CAPT
    "__vector_45": 5,  # TIMER4_OVF (the plant image's clock): r24, SREG
    "__vector_50": 5,  # TIMER5_OVF (the clock)
    "__vector_47": 3,  # TIMER5_COMPA: reti
    "__vector_42": 6,  # TIMER4_COMPA: r24, SREG, r25, all popped before its jmp to __vector_compare_rest
    "__vector_25": 8,  # USART0_RX: r24, SREG, r25, r30, r31
    "__vector_26": 8,  # USART0_UDRE: the same
    "__vector_default": 3,  # BADISR: drive off, waits for the watchdog (never returns)
}
# The handlers that turn interrupts on, and the enable bit each masks first: (register, bit).
TIMSK4, TIMSK5, UCSR0B = 0x72, 0x73, 0xC1
SELF_MASKING = {
    "__vector_41": (TIMSK4, 5),  # ICIE4
    "__vector_46": (TIMSK5, 5),  # ICIE5
    "__vector_25": (UCSR0B, 7),  # RXCIE0
    "__vector_26": (UCSR0B, 5),  # UDRIE0
}
FUNC = re.compile(r"^[0-9a-f]+ <(?P<name>[^>]+)>:$")
CALL = re.compile(r"\s(?:call|rcall|jmp|rjmp)\s.*<(?P<name>[^>+]+)>")
ANDI = re.compile(r"\tandi\tr(?P<r>\d+), 0x(?P<k>[0-9A-Fa-f]+)")
STS = re.compile(r"\tsts\t0x(?P<a>[0-9A-Fa-f]+), r(?P<r>\d+)")


def masks_itself_first(body: list[str], reg: int, bit: int) -> bool:
    """Whether, before its first `sei`, the handler clears `bit` of `reg` (andi, then sts)."""
    cleared: set[int] = set()
    for line in body:
        if re.search(r"\tsei\b", line):
            return False
        if (m := ANDI.search(line)) and not int(m["k"], 16) & (1 << bit):
            cleared.add(int(m["r"]))
        if (m := STS.search(line)) and int(m["a"], 16) == reg and int(m["r"]) in cleared:
            return True
    return False


def main(argv: list[str]) -> int:
    elf, su = argv[1], argv[2]
    objdump = argv[3] if len(argv) > 3 else "avr-objdump"
    frames: dict[str, int] = {}
    for line in Path(su).read_text().splitlines():
        where, size, _ = line.split("\t")
        name = where.rsplit(":", 1)[1]
        frames[name] = max(frames.get(name, 0), int(size))
    calls: dict[str, set[str]] = {}
    bodies: dict[str, list[str]] = {}
    seis: set[str] = set()
    cur = None
    for line in subprocess.run(
        [objdump, "-d", elf], capture_output=True, text=True, check=True
    ).stdout.splitlines():
        m = FUNC.match(line)
        if m:
            cur = m["name"]
            calls.setdefault(cur, set())
            bodies.setdefault(cur, [])
            continue
        if cur is None:
            continue
        bodies[cur].append(line)
        c = CALL.search(line)
        if c and c["name"] != cur:
            calls[cur].add(c["name"])
        if re.search(r"\tsei\b", line):
            seis.add(cur)

    def skip(f: str, g: str) -> bool:  # the vector table's jumps, and the bad-interrupt loop
        if re.fullmatch(r"__vector_\d+", g) and g not in HAND_WRITTEN and f != "__vectors":
            return True
        return g == "__vectors" or g.startswith("__bad_interrupt")

    def depth(f: str, seen: tuple[str, ...] = ()) -> tuple[int, list[str]]:
        if f in seen:
            raise SystemExit(f"stack_depth: recursion through {f}: no bound")
        own = HAND_WRITTEN.get(f, frames.get(f, 0))
        best, chain = 0, []
        for g in sorted(calls.get(f, ())):
            if skip(f, g):
                continue
            d, ch = depth(g, (*seen, f))
            if d > best:
                best, chain = d, ch
        return own + best, [f, *chain]

    def turns_interrupts_on(f: str, seen: tuple[str, ...] = ()) -> bool:  # it, or what it calls
        if f in seis:
            return True
        return any(
            turns_interrupts_on(g, (*seen, f)) for g in calls.get(f, ()) if g not in seen and not skip(f, g)
        )

    main_d, main_chain = depth("main")
    isrs = sorted({f for f in calls if re.fullmatch(r"__vector_\d+", f)} | (set(HAND_WRITTEN) & set(calls)))
    nesting = [f for f in isrs if turns_interrupts_on(f)]
    for f in nesting:
        if f not in SELF_MASKING:
            raise SystemExit(f"stack_depth: {f} turns interrupts on without masking itself: no bound")
        if not masks_itself_first(bodies[f], *SELF_MASKING[f]):
            reg, bit = SELF_MASKING[f]
            raise SystemExit(
                f"stack_depth: {f} turns interrupts on before it clears bit {bit} of 0x{reg:02X}: no bound"
            )
    others = [f for f in isrs if f not in nesting]
    nest_d = sum(depth(f)[0] for f in nesting)
    other_d, other_chain = max((depth(f) for f in others), default=(0, []))
    total = main_d + nest_d + other_d
    print(
        f"main {main_d} ({' > '.join(main_chain)}), the self-masking handlers once each "
        f"({' + '.join(f'{f} {depth(f)[0]}' for f in nesting) or '-'}) {nest_d}, "
        f"then the deepest of the others {other_d} ({' > '.join(other_chain)}): {total} bytes",
        file=sys.stderr,
    )
    print(total)
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv))
