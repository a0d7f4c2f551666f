"""A linear programme solved again and again, each time from the last one's basis: `fcemu bound`'s.

The bound solves a command's programme without the gyroscopic term, then again with McCormick's
rows over the command's rate boxes added, and the boxes' programmes again with other costs. HiGHS
(highspy) keeps the model and its optimal basis between solves, so each starts from the last one's
vertex instead of from scratch, as `scipy.optimize.linprog` does.

Rows marked lazy (the tangent cuts under k_F·ω², most of the programme's rows and few of them
binding) enter the model only once a solution violates them, and leave it once an optimum does not
need them (kept, the box programme of one 7-inch command took on ten times the rows it ends with). The
optimum is then the whole programme's: a solution that violates no lazy row is feasible for the
whole programme and optimal for a relaxation of it. A solve stopped short of that would still
be a relaxation's optimum, so a lower bound, never above the whole programme's.
"""

from __future__ import annotations

import ctypes
import os
import sys

import highspy
import numpy as np
from scipy import sparse

INF = highspy.kHighsInf
LAZY_TOLERANCE = 1e-9  # of a lazy row's scale: a violation under it is the solver's rounding
MOST_ROUNDS = 50  # of lazy rows added per solve; a few are usual


def _finite(values: np.ndarray) -> np.ndarray:
    out = np.asarray(values, dtype=float).copy()
    out[out == np.inf], out[out == -np.inf] = INF, -INF
    return out


def quiet_highs() -> highspy.Highs:
    """A HiGHS model that prints nothing. Its first one in a process prints HiGHS's banner on stdout
    from C++, before any option can turn it off: that goes to /dev/null, not where `--json` prints."""
    sys.stdout.flush()
    saved = os.dup(1)
    try:
        with open(os.devnull, "w") as null:
            os.dup2(null.fileno(), 1)
            highs = highspy.Highs()
            ctypes.CDLL(None).fflush(None)
    finally:
        os.dup2(saved, 1)
        os.close(saved)
    highs.setOptionValue("output_flag", False)
    return highs


class Programme:
    """min c·x subject to A_ub·x ≤ b_ub, A_eq·x = b_eq and bounds, warm-started between solves."""

    def __init__(self, A_ub: sparse.csr_matrix, b_ub: np.ndarray, A_eq: sparse.csr_matrix, b_eq: np.ndarray,
                 bounds: np.ndarray, lazy: np.ndarray, scale: float, time_limit_s: float) -> None:
        """`lazy`: a mask over the rows of A_ub; `scale`: the size of their right-hand sides, for the
        tolerance; `time_limit_s`: past this the simplex is stopped and the interior-point method
        solves the programme (HiGHS's simplex stalls on a few degenerate ones)."""
        self.n = A_ub.shape[1]
        self.eager = np.flatnonzero(~lazy)
        self.lazy_rows, self.lazy_rhs = A_ub[lazy], b_ub[lazy]
        self.tolerance = LAZY_TOLERANCE * scale
        self.time_limit_s = time_limit_s
        self.highs = quiet_highs()
        self.highs.addVars(self.n, _finite(bounds[:, 0]), _finite(bounds[:, 1]))
        self._add_rows(A_eq, b_eq, b_eq)
        eager = A_ub[self.eager]
        self._add_rows(eager, np.full(eager.shape[0], -INF), b_ub[self.eager])
        self.base_rows = self.highs.getNumRow()
        self.added = np.zeros(self.lazy_rows.shape[0], dtype=bool)  # lazy rows ever added
        self.in_model: list[int] = []  # each row after the base rows: its lazy row, or -1 (an extra row)
        self.row_of_ub = np.full(A_ub.shape[0], -1)
        self.row_of_ub[self.eager] = A_eq.shape[0] + np.arange(len(self.eager))

    def _add_rows(self, A: sparse.csr_matrix, lower: np.ndarray, upper: np.ndarray) -> None:
        A = sparse.csr_matrix(A)
        if A.shape[0]:
            self.highs.addRows(A.shape[0], _finite(lower), _finite(upper), A.nnz,
                               A.indptr[:-1].astype(np.int32), A.indices.astype(np.int32), A.data)

    def solve(self, cost: np.ndarray, ub_rows: np.ndarray, ub_rhs: np.ndarray, bounds: np.ndarray,
              extra: tuple[sparse.csr_matrix, np.ndarray] | None = None) -> np.ndarray | None:
        """The optimal x, or None where the programme is infeasible. `ub_rows`, `ub_rhs`: new right-hand
        sides for those eager rows of A_ub; `bounds` (n, 2) every variable's; `extra`: rows (A, b),
        A·x ≤ b, for this solve only."""
        h = self.highs
        self._delete([i for i, lazy in enumerate(self.in_model) if lazy < 0])
        rows = self.row_of_ub[ub_rows].astype(np.int32)
        assert (rows >= 0).all(), "only eager rows change their right-hand side"
        h.changeRowsBounds(len(rows), rows, np.full(len(rows), -INF), _finite(ub_rhs))
        columns = np.arange(self.n, dtype=np.int32)
        h.changeColsBounds(self.n, columns, _finite(bounds[:, 0]), _finite(bounds[:, 1]))
        h.changeColsCost(self.n, columns, np.asarray(cost, dtype=float))
        if extra is not None:
            A, b = extra
            self._add_rows(A, np.full(A.shape[0], -INF), b)
            self.in_model += [-1] * A.shape[0]
        present = np.zeros(len(self.lazy_rhs), dtype=bool)
        present[[lazy for lazy in self.in_model if lazy >= 0]] = True
        for _ in range(MOST_ROUNDS):
            x = self._run()
            if x is None:
                return None
            slack = self.lazy_rhs - self.lazy_rows @ x
            violated = (slack < -self.tolerance) & ~present
            if not violated.any():
                break
            present |= violated
            self.added |= violated
            self._add_rows(self.lazy_rows[violated], np.full(violated.sum(), -INF), self.lazy_rhs[violated])
            self.in_model += np.flatnonzero(violated).tolist()
        loose = slack > self.tolerance
        self._delete([i for i, lazy in enumerate(self.in_model) if lazy >= 0 and loose[lazy]])
        return x

    def _delete(self, positions: list[int]) -> None:
        """Delete these rows after the base rows (positions in `in_model`)."""
        if not positions:
            return
        self.highs.deleteRows(len(positions), np.array(positions, dtype=np.int32) + self.base_rows)
        gone = set(positions)
        self.in_model = [lazy for i, lazy in enumerate(self.in_model) if i not in gone]

    def _run(self) -> np.ndarray | None:
        h = self.highs
        h.setOptionValue("time_limit", self.time_limit_s)
        h.run()
        status = h.getModelStatus()
        if status == highspy.HighsModelStatus.kTimeLimit:
            h.setOptionValue("time_limit", INF)
            h.setOptionValue("solver", "ipm")
            h.run()
            h.setOptionValue("solver", "choose")
            status = h.getModelStatus()
        if status == highspy.HighsModelStatus.kInfeasible:
            return None
        if status != highspy.HighsModelStatus.kOptimal:
            raise RuntimeError(f"HiGHS: {h.modelStatusToString(status)}")
        return np.array(h.getSolution().col_value)
