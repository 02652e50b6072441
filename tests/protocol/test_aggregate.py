"""A run aggregate's exact sums outgrow 64 bits on a long run (the squared operating times of
~250,000 strokes of 8.5 ms pass 2^64) and must still be kept: the record writer thread died on
`msgpack` OverflowError at 222,698 strokes of a virtual 10^6 run (issue 36's bench)."""

from __future__ import annotations

from usmswitch.protocol.aggregate import ExactRunning, RunAggregate


def test_sums_past_64_bits_round_trip_exactly() -> None:
    agg = RunAggregate()
    big = ExactRunning()
    for x in (8_500_000, -8_400_000, 9_100_000):
        big.add(x)
    big.count += 10**7
    big.s *= 10**7
    big.ss *= 10**12  # ~2e26: far past 2^64
    agg.per[0].operating = big  # type: ignore[assignment]
    back = RunAggregate(agg.to_bytes()).per[0].operating
    assert (back.count, back.s, back.ss, back.max_abs) == (big.count, big.s, big.ss, big.max_abs)  # type: ignore[attr-defined]
    assert back.std == big.std  # type: ignore[attr-defined]


def test_a_long_run_of_strokes_keeps_its_sums() -> None:
    # 300,000 operating times of ~8.5 ms: the squares' sum is ~2.2e19 > 2^64.
    run = ExactRunning()
    for i in range(300_000):
        run.add(8_500_000 + (i % 1000))
    assert run.ss > 1 << 64
    assert ExactRunning(*run.state()).ss == run.ss
