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


def test_a_live_run_and_its_kept_aggregate_say_the_same_figures() -> None:
    # 8 strokes whose mean is an exact half: Welford's floats (the live figures, before) rounded it
    # one 0.1 ns from the kept integer sums (5326.7 live, 5326.8 from the records: a test saw it).
    import random

    from usmswitch.protocol.stats import Running

    rng = random.Random(1)
    for _ in range(500):
        xs = [rng.randint(-200_000, 200_000) for _ in range(8)]
        live, kept = Running(), ExactRunning()
        for x in xs:
            live.add(x)
            kept.add(x)
        assert live.as_dict("error") == ExactRunning(*kept.state()).as_dict("error"), xs


def test_a_dropped_sketch_is_freed_without_the_cyclic_collector() -> None:
    """The daemon runs with the collector off but for the young generations: a sketch (and the
    histogram a decode makes on the way) must go by refcounting alone. hdrh's histogram and its
    encoder referred to each other, and 1,600 sketches were alive after 500 runs."""
    import gc
    import weakref

    from usmswitch.protocol.aggregate import Sketch

    full = Sketch()
    for v in (1_000, 2_000_000, 9_000_000):
        full.add(v)
    encoded = full.encode()
    gc.disable()
    try:
        gc.collect()
        made = Sketch(encoded)
        assert made.quantiles((50,)) == full.quantiles((50,))
        ref = weakref.ref(made.hist)
        del made
        assert ref() is None, "the sketch's histogram waits for the cyclic collector"
        # Nor the one its decode made: only `full`'s is left.
        left = [o for o in gc.get_objects() if type(o).__name__ == "HdrHistogram"]
        assert all(o is full.hist for o in left), left
    finally:
        gc.enable()
