"""Exact least squares on integer normal equations (fraction-free elimination).

Stroke times are ~1e7 ns with ~1e5 ns scatter, so the uncentred normal equations of the paper's model
(Eq. 5) have condition numbers of 1e6 and more for m >= 2: a float solve loses most of its digits.
Here the normal equations are exact Python integers and a fraction-free (Bareiss) elimination keeps
every intermediate an exact integer, so the solution comes out as integer numerators over one integer
determinant and a prediction is one correctly rounded division. Nothing is lost to conditioning.

The lags are eliminated in order 1..m. The normal matrix is positive semidefinite, so a zero pivot
means that lag's column is a linear combination of lower lags over the rows (its whole row is zero
then): it is skipped and its coefficient is 0. That is a basic least-squares solution: its fitted
values and residual sum of squares are those of every least-squares solution.
"""

from __future__ import annotations

from typing import NamedTuple


class ExactSolution(NamedTuple):
    """A least-squares solution a_j = numerators[j-1] / det, exactly (det > 0)."""

    numerators: tuple[int, ...]
    det: int
    dropped: bool  # a dependent lag was dropped (coefficient 0): X^T X was singular


class NormalPlan:
    """Index plan of the fraction-free solve for order m, over a flat (m+1)x(m+1) upper-triangle layout.

    Entry (j, k), j <= k, sits at `j * (m + 1) + k`; index 0 is the target y and 1..m the lags, so
    (0, k) is (X^T y)_k and (j, k) is (X^T X)_jk. The lower triangle and (0, 0) are never read.
    """

    __slots__ = ("back", "gram_pairs", "m", "pairs", "rss_steps", "size", "steps")

    def __init__(self, m: int) -> None:
        self.m = m
        n1 = m + 1
        self.size = n1 * n1

        def at(i: int, j: int) -> int:
            return min(i, j) * n1 + max(i, j)

        # The entries the sums keep: the upper triangle without (0, 0), as (flat index, j, k).
        self.pairs = tuple((at(j, k), j, k) for j in range(n1) for k in range(j, n1) if k)
        #: With (0, 0), y.y: the sums AIC's nested fits need (`gram`, `nested_rss`).
        self.gram_pairs = ((0, 0, 0), *self.pairs)

        def elimination(with_target: bool) -> tuple[tuple[int, tuple[tuple[int, int, int], ...]], ...]:
            steps = []
            for k in range(1, n1):
                rest = [0, *range(k + 1, n1)]
                ups = tuple(
                    (at(i, j), at(i, k), at(k, j))
                    for a, i in enumerate(rest)
                    for j in rest[a:]
                    if with_target or (i, j) != (0, 0)
                )
                steps.append((at(k, k), ups))
            return tuple(steps)

        self.steps = elimination(False)
        self.rss_steps = elimination(True)
        self.back = tuple(
            (k - 1, at(k, k), at(0, k), tuple((at(k, j), j - 1) for j in range(k + 1, n1)))
            for k in range(m, 0, -1)
        )

    def solve(self, a: list[int]) -> tuple[list[int], int, bool]:
        """Solve in place: (numerators, det, dropped) with a_j = numerators[j-1] / det exactly, det > 0."""
        prev = 1
        dropped = False
        for kk, ups in self.steps:
            p = a[kk]
            if not p:
                dropped = True
                continue
            for ij, ik, kj in ups:
                a[ij] = (p * a[ij] - a[ik] * a[kj]) // prev
            prev = p
        num = [0] * self.m
        # Back substitution on the row-scaled triangle: num_k = (det b_k - sum_j U_kj num_j) / U_kk,
        # an exact division because det * a_k is an integer (Cramer's rule).
        for k0, kk, b, row in self.back:
            p = a[kk]
            if p:
                acc = prev * a[b]
                for kj, j0 in row:
                    acc -= a[kj] * num[j0]
                num[k0] = acc // p
        return num, prev, dropped

    def gram(self, columns: list[list[int]]) -> list[int]:
        """Exact sums Z^T Z of integer columns (0 the target, 1..m the lags), (0, 0) included, flat."""
        a = [0] * self.size
        for idx, j, k in self.gram_pairs:
            a[idx] = sum(map(int.__mul__, columns[j], columns[k]))
        return a

    def nested_rss(self, a: list[int]) -> list[tuple[int, int]]:
        """Residual sums of squares of the nested fits on lags 1..k for every k, as exact (num, den).

        `a` holds every sum of `gram` (overwritten). One elimination pass gives every order: after
        eliminating lag k, the target's diagonal entry is det_k * RSS_k. A dependent lag leaves RSS alone.
        """
        prev = 1
        out: list[tuple[int, int]] = []
        add = out.append
        for kk, ups in self.rss_steps:
            p = a[kk]
            if p:
                for ij, ik, kj in ups:
                    a[ij] = (p * a[ij] - a[ik] * a[kj]) // prev
                prev = p
            add((a[0], prev))
        return out


def solve_small(a: list[int], m: int) -> tuple[list[int], int, bool] | None:
    """Orders 2 and 3 in closed form (Cramer's rule on the flat layout of `NormalPlan`): the same
    (numerators, det) as `NormalPlan.solve` when X^T X is regular, in half the time (no divisions);
    None when it is singular (or m is another order), for the elimination to drop a lag."""
    if m == 3:
        a11, a12, a13, a22, a23, a33 = a[5], a[6], a[7], a[10], a[11], a[15]
        b1, b2, b3 = a[1], a[2], a[3]
        c11 = a22 * a33 - a23 * a23
        c12 = a13 * a23 - a12 * a33
        c13 = a12 * a23 - a13 * a22
        det = a11 * c11 + a12 * c12 + a13 * c13
        if det <= 0:
            return None
        c22 = a11 * a33 - a13 * a13
        c23 = a12 * a13 - a11 * a23
        c33 = a11 * a22 - a12 * a12
        return (
            [c11 * b1 + c12 * b2 + c13 * b3, c12 * b1 + c22 * b2 + c23 * b3, c13 * b1 + c23 * b2 + c33 * b3],
            det,
            False,
        )
    if m == 2:
        a11, a12, a22, b1, b2 = a[4], a[5], a[8], a[1], a[2]
        det = a11 * a22 - a12 * a12
        if det <= 0:
            return None
        return [a22 * b1 - a12 * b2, a11 * b2 - a12 * b1], det, False
    return None
