"""The case a session shows: built-in or its own, its output, and where bands are drawn."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import param

from mdcore import _cases as cases
from mdcore._cases import Case

from .session_model import SessionModel

#: Points of the 1-D bands: smooth at a third of the page (points 1 % of the span apart).
GRID_1D = 101
#: Points per axis of the 2-D δ maps: beam-2d's 20 × 20 test grid, so the maps show the very
#: predictions the metrics score, at no second prediction (docs/performance.md).
GRID_2D = 20


class OwnCase(NamedTuple):
    """A case beyond the built-in ones: from a ``--case`` file, or uploaded measurements
    (their CSV and file name) ``based_on`` a built-in case's simulator."""

    case: Case
    based_on: str | None = None
    measurements_csv: str | None = None
    measurements_file: str | None = None


def plotting_grid(case) -> np.ndarray:
    """Inputs (G, d_x) at which the bands are drawn: fine in 1-D, a square grid in 2-D."""
    lo = np.minimum(case.X_train.min(axis=0), case.X_test.min(axis=0))
    hi = np.maximum(case.X_train.max(axis=0), case.X_test.max(axis=0))
    if case.d_x == 1:
        return np.linspace(lo[0], hi[0], GRID_1D)[:, None]
    g1, g2 = np.meshgrid(np.linspace(lo[0], hi[0], GRID_2D), np.linspace(lo[1], hi[1], GRID_2D),
                         indexing="xy")
    return np.column_stack([g1.ravel(), g2.ravel()])


class CaseModel(SessionModel):
    """The case, its output shown and the plotting grid (the views draw ``case``)."""

    case_name = param.Selector(objects=list(cases.names()), default="beam-1d", label="Case study")
    output = param.String(default="", label="Output",
                          doc="The output whose plots are shown, for cases with several "
                              "(shear-5's five modes): one at a time, so each plot is "
                              "readable and a change redraws a few plots, not all.")
    slice_x2 = param.Number(default=0.025, label="Slice at x₂",
                            doc="beam-2d: crack length [m] of the δ slice view.")
    case = param.Parameter(doc="The loaded mdcore Case.")
    grid = param.Array(doc="(G, d_x) inputs at which the bands are drawn (plotting_grid).")

    #: This session's own cases by name (set by ExplorerState).
    _own: dict[str, OwnCase]

    def base_case_name(self) -> str:
        """The built-in case the current case builds on (itself, if built-in)."""
        own = self._own.get(self.case_name)
        return self.case_name if own is None else (own.based_on or self.case_name)

    @property
    def output_index(self) -> int:
        """Index of ``output`` in the case's outputs (``_check_output`` keeps it one)."""
        return self.case.output_names.index(self.output)

    @param.depends("output", watch=True)
    def _check_output(self):
        """An output the case does not have: one notification, and the first output."""
        names = self.case.output_names
        if self.output not in names:
            bad, self.output = self.output, names[0]
            self.report_error(f"Output: {bad!r} is not an output of {self.case.name}; it "
                              f"has {', '.join(names)}. Showing {names[0]}.")

    def _show_case(self, case: Case) -> None:
        """The case-and-data part of loading ``case``: its first output, its grid and
        the δ slice of a 2-D case."""
        self.output = case.output_names[0]
        self.grid = plotting_grid(case)
        if case.d_x == 2:
            self.param.slice_x2.bounds = (float(case.X_train[:, 1].min()),
                                          float(case.X_train[:, 1].max()))
            u2 = np.unique(self.grid[:, 1])     # a row of the grid: the one drawn
            self.slice_x2 = float(u2[np.argmin(np.abs(u2 - np.median(case.X_train[:, 1])))])
