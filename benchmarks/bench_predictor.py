"""Per-stroke cost of update + predict: ARPredictor against refitting the same window, same run.

Peers: a fresh numpy `lstsq` fit of the window on every stroke, and a fresh statsmodels `AutoReg` fit.
Window 100, orders 1 and 3; ours in both models, the targets binding the default (paper) model.
Each stroke is timed alone with perf_counter_ns (the timer pair's ~0.05-0.1 us is included, not
subtracted). Targets (issue 2): AR(1) median <= 1 us, >= 5x faster than the numpy refit and >= 300x
faster than statsmodels; order 3 median <= 8 us.

Then the default model (`DEFAULT_MODEL`, "kalman"; issue 24): update + predict per stroke, told the
stroke's conditions, on the outliers scenario (the default rig with one stroke in ~250 ten floors off,
so the suspect and level-shift paths are timed too): median <= 10 us, and the worst stroke that changes
the chosen filter or takes a suspect <= 50 us, each such stroke timed on 5 copies of the predictor
with gc off and the least kept (a collection or a preemption on this shared machine is not its cost).
Its memory is fixed: the msgpack state after 20,000 strokes is as long as after 1,000.
"""

from __future__ import annotations

import gc
import math
import time
from collections import deque
from collections.abc import Callable

import msgpack
import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from benchmarks.table import print_table
from usmswitch.predictor import DEFAULT_MODEL, ARPredictor, make_predictors
from usmswitch.predictor.kalman import KalmanPredictor
from usmswitch.sim.scenarios import run_scenario

WINDOW = 100
N_OURS = 20_000
N_NUMPY = 3_000
N_STATSMODELS = 300
TARGET_DEFAULT_US = 10.0
TARGET_DEFAULT_WORST_US = 50.0


def _series(n: int, seed: int = 1) -> list[int]:
    rng = np.random.default_rng(seed)
    x = np.zeros(n)
    e = rng.normal(0.0, 1e5, n)
    for i in range(1, n):
        x[i] = 0.7 * x[i - 1] + e[i]
    return [int(v) for v in np.rint(1e7 + x)]


def _time_strokes(step: Callable[[int], float], values: list[int]) -> np.ndarray:
    """Time step(v) for each value alone; microseconds."""
    pc = time.perf_counter_ns
    out = np.empty(len(values))
    for i, v in enumerate(values):
        t0 = pc()
        step(v)
        out[i] = pc() - t0
    return out / 1000.0


def _ours(
    order: int | str, model: str, values: list[int], keep: list[ARPredictor] | None = None
) -> np.ndarray:
    p = ARPredictor(order=order, window=WINDOW, model=model)
    if keep is not None:
        keep.append(p)
    p.extend(values[:WINDOW])
    p.predict()
    update = p.update
    predict = p.predict

    def step(v: int) -> float:
        update(v)
        return predict()

    return _time_strokes(step, values[WINDOW:])


def _numpy_refit(order: int, values: list[int]) -> np.ndarray:
    win: deque[int] = deque(values[:WINDOW], maxlen=WINDOW)

    def step(v: int) -> float:
        win.append(v)
        w = np.array(win, dtype=float)
        lags = sliding_window_view(w, order + 1)[:, ::-1]  # rows (t_i, t_{i-1}, ..., t_{i-m})
        coef = np.linalg.lstsq(lags[:, 1:], lags[:, 0], rcond=None)[0]
        return float(coef @ w[: -order - 1 : -1])

    return _time_strokes(step, values[WINDOW:])


def _statsmodels_refit(order: int, values: list[int]) -> np.ndarray:
    from statsmodels.tsa.ar_model import AutoReg

    win: deque[int] = deque(values[:WINDOW], maxlen=WINDOW)

    def step(v: int) -> float:
        win.append(v)
        w = np.array(win, dtype=float)
        params = AutoReg(w, lags=order, trend="n").fit().params
        return float(params @ w[: -order - 1 : -1])

    return _time_strokes(step, values[WINDOW:])


def _check_peers_agree(order: int, values: list[int]) -> None:
    """The peers compute the same t_hat as ours (else the comparison means nothing)."""
    p = ARPredictor(order=order, window=WINDOW)
    p.extend(values[: WINDOW + 50])
    w = np.array(values[50 : WINDOW + 50], dtype=float)
    lags = sliding_window_view(w, order + 1)[:, ::-1]
    coef = np.linalg.lstsq(lags[:, 1:], lags[:, 0], rcond=None)[0]
    ref = float(coef @ w[: -order - 1 : -1])
    if abs(p.predict() - ref) > 1e-9 * ref:
        raise AssertionError(f"numpy peer disagrees: {p.predict()} vs {ref}")


def _default_cost() -> tuple[np.ndarray, list[float], int, int]:
    """(us per stroke, us of each stroke that re-selects or takes a suspect (least of 5 copies), state
    bytes after 1,000 and after 20,000 strokes) of the default model on the outliers scenario."""
    strokes = [
        s for seed in (1, 2, 3, 4, 5) for s in run_scenario("outliers", seed=seed, cycles=4000).strokes
    ]
    ps = make_predictors(DEFAULT_MODEL, [8_000_000, 8_000_000])
    pc = time.perf_counter_ns
    each = np.empty(len(strokes))
    special: list[float] = []
    sizes = {}
    for i, s in enumerate(strokes):
        p = ps[s.direction]
        if isinstance(p, KalmanPredictor) and i > 200 and i % 7 == 0:
            # Time this stroke's copies too when it re-selects or takes a suspect (known only after).
            copies = [KalmanPredictor.from_state(p.state()) for _ in range(5)]
            before = (p._best, p._pending)
        else:
            copies = []
        t0 = pc()
        p.predict(s.conditions)
        p.update(s.operating_ns, s.conditions)
        each[i] = pc() - t0
        if copies and (p._best, p._pending) != before:
            gc.disable()
            try:
                best = math.inf
                for q in copies:
                    t0 = pc()
                    q.predict(s.conditions)
                    q.update(s.operating_ns, s.conditions)
                    best = min(best, pc() - t0)
            finally:
                gc.enable()
            special.append(best / 1000.0)
        if i + 1 in (1000, len(strokes)):
            sizes[i + 1] = len(msgpack.packb(p.state()))
    return each[400:] / 1000.0, special, sizes[1000], sizes[len(strokes)]


def main() -> int:
    """Measure, print the table, and return 1 if a target is missed."""
    values = _series(N_OURS + WINDOW)
    rows: list[list[object]] = []
    missed: list[str] = []
    for order, target_us in ((1, 1.0), (3, 8.0)):
        _check_peers_agree(order, values)
        ours = {model: _ours(order, model, values) for model in ("paper", "centered")}
        peers = {
            "numpy lstsq refit": _numpy_refit(order, values[: N_NUMPY + WINDOW]),
            "statsmodels AutoReg refit": _statsmodels_refit(order, values[: N_STATSMODELS + WINDOW]),
        }
        base = float(np.median(ours["paper"]))
        for model, t in ours.items():
            med = float(np.median(t))
            ok = med <= target_us
            # The targets are the issue's, for the default (paper) model; centered is shown beside it.
            if model == "paper":
                target = f"median <= {target_us:g} us"
                verdict = "ok" if ok else "MISSED"
                if not ok:
                    missed.append(f"AR({order}) {model} median {med:.2f} us > {target_us} us")
            else:
                target = f"(info; {target_us:g} us)"
                verdict = "within" if ok else "over"
            rows.append(
                [f"ARPredictor {model}", order, len(t), f"{med:.2f}", f"{np.percentile(t, 99):.2f}",
                 f"{med / base:.2f}", target, verdict]
            )  # fmt: skip
        for name, t in peers.items():
            med = float(np.median(t))
            ratio = med / base
            target = ""
            ok = True
            if order == 1:
                need = 5.0 if name.startswith("numpy") else 300.0
                target = f"ours >= {need:g}x faster"
                ok = ratio >= need
                if not ok:
                    missed.append(f"AR(1) only {ratio:.1f}x faster than {name} (need {need:g}x)")
            rows.append(
                [name, order, len(t), f"{med:.2f}", f"{np.percentile(t, 99):.2f}", f"{ratio:.1f}",
                 target, ("ok" if ok else "MISSED") if target else ""]
            )  # fmt: skip
    # Online order selection: a stroke that re-selects (every 100 here) pays for the AIC table.
    kept: list[ARPredictor] = []
    auto = _ours("auto", "paper", values, kept)
    rows.append(
        ["ARPredictor paper auto (reselect 100)", f"1..8, now {kept[0].order}", len(auto),
         f"{np.median(auto):.2f}", f"{np.percentile(auto, 99):.2f}", "",
         f"max {auto.max():.0f} us (a re-selecting stroke)", ""]
    )  # fmt: skip
    t, special, small, large = _default_cost()
    med = float(np.median(t))
    worst = max(special)
    ok_med, ok_worst, ok_mem = med <= TARGET_DEFAULT_US, worst <= TARGET_DEFAULT_WORST_US, small == large
    rows.append(
        [f"{DEFAULT_MODEL} (default), outliers scenario", "1", len(t), f"{med:.2f}",
         f"{np.percentile(t, 99):.2f}", "", f"median <= {TARGET_DEFAULT_US:g} us",
         "ok" if ok_med else "MISSED"]
    )  # fmt: skip
    rows.append(
        [f"{DEFAULT_MODEL}: a stroke that re-selects or takes a suspect", "1", len(special),
         f"{np.median(special):.2f}", f"max {worst:.1f}", "",
         f"max <= {TARGET_DEFAULT_WORST_US:g} us", "ok" if ok_worst else "MISSED"]
    )  # fmt: skip
    rows.append(
        [f"{DEFAULT_MODEL}: msgpack state bytes, 1,000 / {len(t) + 400:,} strokes", "", "", "", "", "",
         f"{small} / {large} (fixed)", "ok" if ok_mem else "MISSED"]
    )  # fmt: skip
    if not ok_med:
        missed.append(f"{DEFAULT_MODEL} median {med:.2f} us > {TARGET_DEFAULT_US:g} us")
    if not ok_worst:
        missed.append(
            f"{DEFAULT_MODEL} worst re-selecting stroke {worst:.1f} us > {TARGET_DEFAULT_WORST_US:g} us"
        )
    if not ok_mem:
        missed.append(f"{DEFAULT_MODEL} state grew: {small} -> {large} bytes")
    print_table(
        ["predictor", "order", "strokes", "median us", "p99 us", "x ours(paper)", "target", ""],
        rows,
        title=f"update + predict per stroke, window {WINDOW} (timer pair included)",
    )
    for m in missed:
        print(f"TARGET MISSED: {m}")
    return 1 if missed else 0
