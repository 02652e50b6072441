"""Fixed-memory AR(m) predictor of the next stroke's operating time (paper Section 5, Eq. 2-9).

The window holds the last `window` strokes t_1..t_n (oldest first). An AR(m) fit regresses
t_i on (t_{i-1}, ..., t_{i-m}) for i = m+1..n: n - m rows, exactly the design matrix of Eq. 3 and of a
fresh `numpy.linalg.lstsq` or statsmodels `AutoReg(window, lags=m)` fit of the same window.

Each update adds the newest row and removes the row that left the window from exact integer sums
(X^T X and X^T y, plus the column sums for the "centered" model): O(m^2) integer operations, no refit,
no growth, and no drift however long it runs, because integers do not round. The fit is solved exactly
(`exact.NormalPlan.solve`, fraction-free) at the first predict() or coefficients after an update and
cached; t_hat is one correctly rounded integer division. The paper's AR(1) solves inside update().
"""

from __future__ import annotations

from typing import Any

from .aic import AicTable, aic_values, fit_table, min_samples
from .checks import MAX_ORDER, MAX_T_NS, check_int, check_model, check_stroke_ns, check_strokes
from .conditions import Conditions
from .exact import ExactSolution, NormalPlan, solve_small

STATE_FORMAT = "usmswitch.predictor.ar/1"
# One index plan per order, shared by every predictor.
_PLANS = {m: NormalPlan(m) for m in range(1, MAX_ORDER + 1)}
#: Strokes a model with more parameters than the paper's AR(1) waits for before its own fit predicts.
SOUND_FIT = 30


class ARPredictor:
    """Limited-memory AR(m) least squares over the last `window` strokes, updated in O(m^2) per stroke.

    - `model="paper"`: Eq. 2 exactly, t_i = a_1 t_{i-1} + ... + a_m t_{i-m}, no intercept.
    - `model="centered"`: t_i = c + a_1 t_{i-1} + ... + a_m t_{i-m}, the intercept c fitted by least
      squares (a column of ones in X). `coefficients` is then (c, a_1, ..., a_m): intercept first, as
      in statsmodels' `AutoReg(trend="c").params` and in `lstsq` on [1, X].
    - `order="auto"`: start at order 1 (the paper's choice) and re-select the order by AIC (Eq. 8,
      see `aic_table`) over the current window as soon as it holds `2 * max_order + 2` strokes (one more
      for "centered"), then every `reselect_every` strokes. The window is kept; only the sums of the
      new order are rebuilt from it.

    Cold start: until the window holds `min_ready` strokes, `ready` is False, `coefficients` is () and
    `predict()` falls back: `nominal_ns` before the first stroke (with no nominal it raises
    RuntimeError: configure one), the last stroke while fewer than 3 strokes are in, then the paper's
    AR(1) over the window. `min_ready` is `min(window, 3)` for the paper's AR(1) (one residual degree of
    freedom) and `min(window, max(2m + 1 + c, SOUND_FIT))` for every model with more parameters, whose
    fit on the bare minimum of rows errs far more than the AR(1) it replaces.

    Degenerate windows never give NaN or raise: a lag whose column is a linear combination of lower
    lags over the window (constant series, too few rows) gets coefficient 0 and `degenerate` is True.
    A constant window then predicts that constant (paper: a_1 = 1; centered: the intercept).
    """

    __slots__ = (
        "_ag",
        "_as",
        "_auto",
        "_buf",
        "_c",
        "_coef",
        "_coef_seen",
        "_count",
        "_det",
        "_dirty",
        "_dropped",
        "_fast1",
        "_fast1c",
        "_g",
        "_m",
        "_max_order",
        "_min_ready",
        "_model",
        "_nominal",
        "_num",
        "_pending",
        "_plan",
        "_pos",
        "_reselect_every",
        "_s",
        "_seen",
        "_since_select",
        "_sol_seen",
        "_t_hat",
        "_table",
        "_table_seen",
        "_values",
        "_values_seen",
        "_window",
    )

    def __init__(
        self,
        order: int | str = 1,
        window: int = 100,
        model: str = "paper",
        nominal_ns: int | None = None,
        max_order: int = MAX_ORDER,
        reselect_every: int = 100,
    ) -> None:
        self._model = check_model(model)
        self._c = 1 if model == "centered" else 0
        self._max_order = check_int("max_order", max_order, 1, MAX_ORDER)
        self._auto = order == "auto"
        if self._auto:
            m = 1
            need = min_samples(self._max_order, model)
            if not isinstance(window, int) or isinstance(window, bool) or window < need:
                raise ValueError(
                    f"window must be an integer >= {need} for order='auto' with max_order={max_order} "
                    f"and model={model!r}, got {window!r}"
                )
        else:
            if isinstance(order, str):
                raise ValueError(f"order must be an integer in 1..{MAX_ORDER} or 'auto', got {order!r}")
            m = check_int("order", order, 1, MAX_ORDER)
            check_int("window", window, m + 2)
        self._window = window
        self._nominal = None if nominal_ns is None else check_stroke_ns(nominal_ns)
        self._reselect_every = check_int("reselect_every", reselect_every, 1)
        self._buf = [0] * window
        self._pos = 0  # where the next stroke goes; when the window is full, also the oldest stroke
        self._count = 0
        self._seen = 0
        self._since_select: int | None = None
        self._pending: int | None = None  # an order AIC chose, taken at the next stroke
        self._table: AicTable | None = None
        self._table_seen = -1
        self._values: tuple[tuple[float, ...], tuple[float, ...]] = ((), ())
        self._values_seen = -1
        self._set_order(m)
        self._build_aic_sums()

    # ---- configuration -------------------------------------------------------------------------

    def _set_order(self, m: int) -> None:
        """Switch to order m and rebuild its sums from the window (exact, O(n m^2))."""
        plan = _PLANS[m]
        samples = self.samples()
        n = len(samples)
        # Column j holds lag j over the rows i = m..n-1 (column 0 the target); dot products in C.
        cols = [samples[m - j : n - j] for j in range(m + 1)] if n > m else [[] for _ in range(m + 1)]
        g = [0] * plan.size
        for idx, j, k in plan.pairs:
            g[idx] = sum(map(int.__mul__, cols[j], cols[k]))
        self._install(m, g, [sum(c) for c in cols])

    def _install(self, m: int, g: list[int], s: list[int]) -> None:
        """Take order m with its exact sums g (X^T X, X^T y by plan index) and s (column sums)."""
        self._m = m
        self._plan = _PLANS[m]
        self._fast1 = m == 1 and not self._c
        self._fast1c = m == 1 and bool(self._c)
        need = 2 * m + 1 + self._c
        self._min_ready = min(self._window, need if self._fast1 else max(need, SOUND_FIT))
        self._g = g
        self._s = s
        self._dirty = True
        self._coef: tuple[float, ...] = ()
        self._coef_seen = -1
        self._sol_seen = -1
        self._num: list[int] = []
        self._det = 1
        self._dropped = False

    def _build_aic_sums(self) -> None:
        """For `auto`: the exact sums of AIC's common rows (rows M..n-1, lags 0..M), the upper triangle
        in the flat layout of `NormalPlan(M)`, kept up to date by `update` in O(M^2), so that a
        re-selection never passes over the window (O(M^3) only)."""
        if not self._auto:
            self._ag: list[int] = []
            self._as: list[int] = []
            return
        big_m = self._max_order
        x = self.samples()
        n = len(x)
        cols = [x[big_m - j : n - j] if n > big_m else [] for j in range(big_m + 1)]
        self._ag = _PLANS[big_m].gram(cols)
        self._as = [sum(c) for c in cols]

    def _aic_slide(self, t: int, buf: list[int], pos: int, count: int, w: int) -> None:
        """Before `t` is written at `pos`: drop the common row that leaves a full window, add t's row.
        buf[pos - j] is the j-th newest stroke (a negative index wraps a full window, as wanted)."""
        big_m = self._max_order
        if count < big_m:
            return
        ag = self._ag
        sums = self._as
        if count == w and big_m == 3:
            # The daemon's max_order, unrolled (a third of the loop's cost); the layout of NormalPlan(3).
            n1 = buf[pos - 1]
            n2 = buf[pos - 2]
            n3 = buf[pos - 3]
            o3 = buf[pos - w]
            o2 = buf[pos + 1 - w]
            o1 = buf[pos + 2 - w]
            o0 = buf[pos + 3 - w]
            ag[0] += t * t - o0 * o0
            ag[1] += t * n1 - o0 * o1
            ag[2] += t * n2 - o0 * o2
            ag[3] += t * n3 - o0 * o3
            ag[5] += n1 * n1 - o1 * o1
            ag[6] += n1 * n2 - o1 * o2
            ag[7] += n1 * n3 - o1 * o3
            ag[10] += n2 * n2 - o2 * o2
            ag[11] += n2 * n3 - o2 * o3
            ag[15] += n3 * n3 - o3 * o3
            sums[0] += t - o0
            sums[1] += n1 - o1
            sums[2] += n2 - o2
            sums[3] += n3 - o3
            return
        new = [t, *[buf[pos - j] for j in range(1, big_m + 1)]]
        if count == w:
            # The leaving row (o_M, ..., o_0) of the old window, o_k = buf[(pos + k) % w] = buf[pos + k - w].
            top = pos + big_m - w
            old = [buf[top - j] for j in range(big_m + 1)]
            for idx, i, j in _PLANS[big_m].gram_pairs:
                ag[idx] += new[i] * new[j] - old[i] * old[j]
            for i in range(big_m + 1):
                sums[i] += new[i] - old[i]
        else:
            for idx, i, j in _PLANS[big_m].gram_pairs:
                ag[idx] += new[i] * new[j]
            for i in range(big_m + 1):
                sums[i] += new[i]

    def _set_order_from_aic(self, m: int) -> None:
        """Switch to order m from AIC's sums: rows m..n-1 are AIC's rows M..n-1 plus rows m..M-1."""
        plan = _PLANS[m]
        big_m = self._max_order
        n1 = big_m + 1
        # The oldest M strokes of the window: the rows AIC holds back.
        x = self._buf[: self._count] if self._count < self._window else self._oldest(big_m)
        ag = self._ag
        g = [0] * plan.size
        for idx, j, k in plan.pairs:
            g[idx] = ag[j * n1 + k] + sum([x[i - j] * x[i - k] for i in range(m, big_m)])
        s = [self._as[j] + sum(x[m - j : big_m - j]) for j in range(m + 1)]
        self._install(m, g, s)

    def _oldest(self, k: int) -> list[int]:
        """The oldest k strokes of a full window, oldest first."""
        buf = self._buf
        pos = self._pos
        head = buf[pos : pos + k]
        return head if len(head) == k else head + buf[: k - len(head)]

    @property
    def order(self) -> int:
        """The AR order in use now (the selected one when `auto`)."""
        return self._m

    @property
    def auto(self) -> bool:
        """True when the order is re-selected online by AIC."""
        return self._auto

    @property
    def model(self) -> str:
        """'paper' (Eq. 2, no intercept) or 'centered' (with a least-squares intercept)."""
        return self._model

    @property
    def window(self) -> int:
        """Capacity of the window in strokes (N of the limited memory)."""
        return self._window

    @property
    def max_order(self) -> int:
        """Largest order AIC considers (and the hold-back of its common rows)."""
        return self._max_order

    @property
    def reselect_every(self) -> int:
        """Strokes between online order selections when `auto`."""
        return self._reselect_every

    @property
    def nominal_ns(self) -> int | None:
        """The cold-start prediction, if configured."""
        return self._nominal

    @property
    def count(self) -> int:
        """Strokes in the window now (<= window)."""
        return self._count

    @property
    def seen(self) -> int:
        """Strokes ever given to this predictor (including those that left the window)."""
        return self._seen

    @property
    def min_ready(self) -> int:
        """Strokes the window must hold before predictions come from the fit (see `ready`)."""
        return self._min_ready

    @property
    def ready(self) -> bool:
        """False while predict() returns the cold-start nominal instead of a fit."""
        return self._count >= self._min_ready

    # ---- the hot path --------------------------------------------------------------------------

    def update(self, t_ns: int, conditions: Conditions | None = None) -> None:
        """Add the newest stroke's operating time (ns); the oldest leaves a full window. O(m^2).

        `conditions` are taken and not used: Eq. 2 knows only the strokes.
        """
        if type(t_ns) is not int or t_ns <= 0 or t_ns > MAX_T_NS:
            t_ns = check_stroke_ns(t_ns)
        buf = self._buf
        pos = self._pos
        w = self._window
        nxt = pos + 1 if pos + 1 < w else 0
        if self._auto:
            self._aic_slide(t_ns, buf, pos, self._count, w)
        if self._fast1 and self._count == w:
            # The daemon's steady state with the paper's AR(1), unrolled, t_hat solved at once:
            # g[1] = sum x y, g[3] = sum x^2 over the rows (x = t_{i-1}, y = t_i).
            g = self._g
            x = buf[pos - 1]  # the newest stroke so far; pos - 1 == -1 wraps to the end, as wanted
            o1 = buf[pos]  # the oldest row: regressor o1, target o0
            o0 = buf[nxt]
            g[1] = xy = g[1] + t_ns * x - o0 * o1
            g[3] = xx = g[3] + x * x - o1 * o1
            buf[pos] = t_ns
            self._pos = nxt
            self._seen += 1
            self._t_hat = xy * t_ns / xx  # one rounding: xy * t_ns is exact, int / int rounds once
            self._dirty = False
        elif self._fast1c and self._count == w:
            # The same for the centered AR(1); s = [sum y, sum x] too.
            g = self._g
            s = self._s
            x = buf[pos - 1]
            o1 = buf[pos]
            o0 = buf[nxt]
            g[1] = xy = g[1] + t_ns * x - o0 * o1
            g[3] = xx = g[3] + x * x - o1 * o1
            s[0] = sy = s[0] + t_ns - o0
            s[1] = sx = s[1] + x - o1
            buf[pos] = t_ns
            self._pos = nxt
            self._seen += 1
            rows = w - 1
            cxx = rows * xx - sx * sx  # rows^2 var(x), exact
            if cxx:
                # mean(y) + a (t - mean(x)) with a = cxy / cxx, as one exact fraction
                self._t_hat = (cxx * sy + (rows * xy - sx * sy) * (rows * t_ns - sx)) / (rows * cxx)
                self._dirty = False
            else:
                self._dirty = True  # constant regressors: the degenerate fallback in _refresh
        else:
            self._push(t_ns, buf, pos, nxt, w)
        if self._auto:
            self._tick()

    def _push(self, t: int, buf: list[int], pos: int, nxt: int, w: int) -> None:
        """The general update: row out, row in, on g (X^T X and X^T y) and s (column sums)."""
        count = self._count
        g = self._g
        s = self._s
        m = self._m
        if m == 1:
            # Unrolled: g[1] = sum x y, g[3] = sum x^2; s = [sum y, sum x].
            if count == w:
                o1 = buf[pos]
                o0 = buf[nxt]
                g[1] -= o0 * o1
                g[3] -= o1 * o1
                s[0] -= o0
                s[1] -= o1
            if count:
                x = buf[pos - 1]
                g[1] += t * x
                g[3] += x * x
                s[0] += t
                s[1] += x
            buf[pos] = t
            self._pos = nxt
            if count < w:
                self._count = count + 1
            self._seen += 1
            self._dirty = True
            return
        if count == w and m <= 3:
            # Orders 2 and 3 with a full window, unrolled (the general loop below costs twice as
            # much): the row (o0, o1, ..., om) leaves, (t, n1, ..., nm) comes in. buf[pos + k - w]
            # is buf[(pos + k) % w] for k < w, without the modulo.
            n1 = buf[pos - 1]
            n2 = buf[pos - 2]
            if m == 3:
                n3 = buf[pos - 3]
                o3 = buf[pos]
                o2 = buf[pos + 1 - w]
                o1 = buf[pos + 2 - w]
                o0 = buf[pos + 3 - w]
                # The flat layout of NormalPlan(3): (j, k) at 4 j + k.
                g[1] += t * n1 - o0 * o1
                g[2] += t * n2 - o0 * o2
                g[3] += t * n3 - o0 * o3
                g[5] += n1 * n1 - o1 * o1
                g[6] += n1 * n2 - o1 * o2
                g[7] += n1 * n3 - o1 * o3
                g[10] += n2 * n2 - o2 * o2
                g[11] += n2 * n3 - o2 * o3
                g[15] += n3 * n3 - o3 * o3
                s[3] += n3 - o3
            else:
                o2 = buf[pos]
                o1 = buf[pos + 1 - w]
                o0 = buf[pos + 2 - w]
                # The flat layout of NormalPlan(2): (j, k) at 3 j + k.
                g[1] += t * n1 - o0 * o1
                g[2] += t * n2 - o0 * o2
                g[4] += n1 * n1 - o1 * o1
                g[5] += n1 * n2 - o1 * o2
                g[8] += n2 * n2 - o2 * o2
            s[0] += t - o0
            s[1] += n1 - o1
            s[2] += n2 - o2
            buf[pos] = t
            self._pos = nxt
            self._seen += 1
            self._dirty = True
            return
        pairs = self._plan.pairs
        if count == w:
            old = [buf[(pos + m - j) % w] for j in range(m + 1)]  # (target, lag 1, ..., lag m)
            for idx, j, k in pairs:
                g[idx] -= old[j] * old[k]
            for j in range(m + 1):
                s[j] -= old[j]
        if count >= m:
            new = [t, *[buf[pos - j] for j in range(1, m + 1)]]
            for idx, j, k in pairs:
                g[idx] += new[j] * new[k]
            for j in range(m + 1):
                s[j] += new[j]
        buf[pos] = t
        self._pos = nxt
        if count < w:
            self._count = count + 1
        self._seen += 1
        self._dirty = True

    def predict(self, conditions: Conditions | None = None) -> float:
        """t_hat of the next stroke in ns (Eq. 6), or the cold-start fallback while not `ready`.

        `conditions` are taken and not used: Eq. 2 knows only the strokes.
        """
        if self._dirty:
            self._refresh()
        return self._t_hat

    def _refresh(self) -> None:
        """Solve the normal equations exactly and form t_hat (one rounding, in the last division)."""
        count = self._count
        if count < self._min_ready:
            self._t_hat = self._cold_t_hat()
            self._dirty = False
            return
        m = self._m
        buf = self._buf
        pos = self._pos
        num, det, _ = self._solve()
        if self._c == 0:
            acc = 0
            for j in range(m):
                acc += num[j] * buf[pos - 1 - j]
            self._t_hat = acc / det
        else:
            # t_hat = mean(y) + a . (x - mean(x)) = (det sy + sum num_j (rows x_j - s_j)) / (rows det)
            rows = count - m
            s = self._s
            acc = det * s[0]
            for j in range(m):
                acc += num[j] * (rows * buf[pos - 1 - j] - s[j + 1])
            self._t_hat = acc / (rows * det)
        self._dirty = False

    def _cold_t_hat(self) -> float:
        """While not ready: the nominal, then the last stroke, then the paper's AR(1) over the window."""
        count = self._count
        if count == 0:
            if self._nominal is None:
                raise RuntimeError("predict() needs nominal_ns or at least one stroke")
            return float(self._nominal)
        x = self.samples()
        if count < 3:
            return float(x[-1])
        # Eq. 5 for m = 1 on the window (fewer than SOUND_FIT strokes): a_1 = sum x y / sum x^2, exact.
        xy = sum(map(int.__mul__, x[1:], x[:-1]))
        xx = sum(map(int.__mul__, x[:-1], x[:-1]))
        return xy * x[-1] / xx

    def _solve(self) -> tuple[list[int], int, bool]:
        """(numerators, det, dropped) of the slopes a_j = numerators[j-1] / det, cached per stroke."""
        if self._sol_seen == self._seen:
            return self._num, self._det, self._dropped
        m = self._m
        g = self._g
        if m == 1:
            if not self._c:
                sol = [g[1]], g[3], False  # g[3] = sum x^2 > 0: strokes are positive
            else:
                rows = self._count - 1
                sy, sx = self._s
                xx = rows * g[3] - sx * sx
                sol = ([rows * g[1] - sx * sy], xx, False) if xx else ([0], 1, True)
        else:
            if self._c == 0:
                a = g
            else:
                # Centered: the slopes' normal equations are rows^2 x the covariance, formed exactly.
                rows = self._count - m
                s = self._s
                a = [0] * self._plan.size
                for idx, j, k in self._plan.pairs:
                    a[idx] = rows * g[idx] - s[j] * s[k]
            # Orders 2 and 3 in closed form when regular; the elimination (in place) otherwise.
            sol = solve_small(a, m) or self._plan.solve(a[:])
        self._num, self._det, self._dropped = sol
        self._sol_seen = self._seen
        return sol

    # ---- the fit -------------------------------------------------------------------------------

    @property
    def degenerate(self) -> bool:
        """True when the last fit dropped a dependent lag (singular X^T X; see the class docstring)."""
        return self.ready and self._solve()[2]

    @property
    def solution(self) -> ExactSolution | None:
        """The current fit exactly: a_j = numerators[j-1] / det (slopes only); None while cold."""
        if not self.ready:
            return None
        num, det, dropped = self._solve()
        return ExactSolution(tuple(num), det, dropped)

    @property
    def intercept(self) -> float:
        """The fitted intercept c of the centered model (0.0 for the paper model or while cold)."""
        if self._c == 0 or not self.ready:
            return 0.0
        num, det, _ = self._solve()
        s = self._s
        rows = self._count - self._m
        return (det * s[0] - sum(map(int.__mul__, num, s[1:]))) / (rows * det)

    @property
    def coefficients(self) -> tuple[float, ...]:
        """(a_1..a_m) for "paper", (c, a_1..a_m) for "centered"; () while not `ready` (no fit yet)."""
        seen = self._seen
        if self._coef_seen != seen:
            if self._count < self._min_ready:
                self._coef = ()
            else:
                num, det, _ = self._solve()
                a = tuple([n / det for n in num])
                self._coef = (self.intercept, *a) if self._c else a
            self._coef_seen = seen
        return self._coef

    @property
    def residual_variance(self) -> float:
        """RSS / (n - m) of the current fit over its rows, statsmodels' `sigma2`; 0.0 while cold.

        Computed exactly from the window on demand (O(n m)): it is not on the per-stroke path.
        """
        if not self.ready:
            return 0.0
        m = self._m
        num, det, _ = self._solve()
        x = self.samples()
        rows = len(x) - m
        if self._c:
            k = det * self._s[0] - sum(map(int.__mul__, num, self._s[1:]))
            scale = rows
        else:
            k = 0
            scale = 1
        rss = 0
        for i in range(m, len(x)):
            e = det * x[i] - sum(num[j] * x[i - 1 - j] for j in range(m))
            rss += (scale * e - k) ** 2
        return rss / ((scale * det) ** 2 * rows)

    # ---- order selection -----------------------------------------------------------------------

    def aic_table(self) -> AicTable:
        """Eq. 8 for orders 1..max_order over the window (common rows, see `predictor.aic`)."""
        if self._table is None or self._table_seen != self._seen:
            need = min_samples(self._max_order, self._model)
            if self._auto and self._count >= need:
                n_rows = self._count - self._max_order
                aics, sigma2 = self._aic_values()
                self._table = AicTable(
                    tuple(range(1, self._max_order + 1)), aics, sigma2, n_rows, self._model, "fit"
                )
            else:
                self._table = fit_table(self.samples(), self._max_order, self._model)
            self._table_seen = self._seen
        return self._table

    def aic(self, order: int) -> float:
        """AIC(order) per Eq. 8 over the current window; ValueError if it holds too few strokes."""
        check_int("order", order, 1, self._max_order)
        return self.aic_table().values[order - 1]

    def _tick(self) -> None:
        """Online order selection: first when the window allows it, then every `reselect_every`. The
        order chosen is taken at the next stroke, so no stroke pays for both the table and the switch."""
        if self._pending is not None:
            self._set_order_from_aic(self._pending)
            self._pending = None
        if self._since_select is not None:
            self._since_select += 1
        if self._since_select is None:
            if self._count < min_samples(self._max_order, self._model):
                return
        elif self._since_select < self._reselect_every:
            return
        self._since_select = 0
        aics = self._aic_values()[0]
        best = aics.index(min(aics)) + 1  # the lower order on a tie, as AicTable.best
        if best != self._m:
            self._pending = best

    def _aic_values(self) -> tuple[tuple[float, ...], tuple[float, ...]]:
        """(AIC(m), sigma^2) for m = 1..M from the kept sums, once per stroke (the table's numbers, without
        building the table on the re-selecting stroke)."""
        if self._values_seen != self._seen:
            self._values = aic_values(self._ag, self._as, self._count - self._max_order, self._model)
            self._values_seen = self._seen
        return self._values

    # ---- persistence ---------------------------------------------------------------------------

    def samples(self) -> list[int]:
        """The strokes in the window, oldest first."""
        if self._count < self._window:
            return self._buf[: self._count]
        return self._buf[self._pos :] + self._buf[: self._pos]

    def extend(self, samples: Any) -> None:
        """Feed stored strokes in order (warm start); all are validated before any is taken."""
        for v in check_strokes(samples):
            self.update(v)

    def state(self) -> dict[str, Any]:
        """Plain-typed state (msgpack-safe); `from_state` rebuilds a predictor that predicts identically."""
        return {
            "format": STATE_FORMAT,
            "order": "auto" if self._auto else self._m,
            "current_order": self._m,
            "window": self._window,
            "model": self._model,
            "nominal_ns": self._nominal,
            "max_order": self._max_order,
            "reselect_every": self._reselect_every,
            "samples": self.samples(),
            "seen": self._seen,
            "since_select": self._since_select,
            "pending_order": self._pending,
        }

    @classmethod
    def from_state(cls, d: dict[str, Any]) -> ARPredictor:
        """Rebuild a predictor from `state()`; ValueError naming the field if the state is bad."""
        if not isinstance(d, dict):
            raise ValueError(f"predictor state must be a dict, got {type(d).__name__}")
        fields = (
            "format", "order", "current_order", "window", "model", "nominal_ns",
            "max_order", "reselect_every", "samples", "seen", "since_select",
        )  # fmt: skip
        missing = [f for f in fields if f not in d]
        if missing:
            raise ValueError(f"predictor state lacks {', '.join(missing)}")
        if d["format"] != STATE_FORMAT:
            raise ValueError(f"predictor state format must be {STATE_FORMAT!r}, got {d['format']!r}")
        p = cls(
            order=d["order"],
            window=d["window"],
            model=d["model"],
            nominal_ns=d["nominal_ns"],
            max_order=d["max_order"],
            reselect_every=d["reselect_every"],
        )
        samples = d["samples"]
        if not isinstance(samples, list | tuple) or len(samples) > p._window:
            raise ValueError(f"predictor state samples must be a list of <= {p._window} strokes")
        values = [check_stroke_ns(v) for v in samples]
        current = check_int("current_order", d["current_order"], 1, p._max_order)
        if not p._auto and current != p._m:
            raise ValueError(f"current_order {current!r} differs from order {d['order']!r}")
        seen = check_int("seen", d["seen"], len(values))
        since = d["since_select"]
        if since is not None:
            since = check_int("since_select", since, 0)
        for i, v in enumerate(values):
            p._buf[i] = v
        p._count = len(values)
        p._pos = p._count % p._window
        p._seen = seen
        p._since_select = since
        pending = d.get("pending_order")  # absent from states written before it existed
        if pending is not None:
            pending = check_int("pending_order", pending, 1, p._max_order)
            if not p._auto:
                raise ValueError(f"pending_order {pending!r} needs order='auto'")
        p._pending = pending
        p._set_order(current)
        p._build_aic_sums()
        return p

    def __repr__(self) -> str:
        order = f"'auto' (now {self._m})" if self._auto else str(self._m)
        return (
            f"ARPredictor(order={order}, window={self._window}, model={self._model!r}, "
            f"count={self._count}, ready={self.ready})"
        )
