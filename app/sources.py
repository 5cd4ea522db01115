"""Bokeh data sources and ranges changed in place, sending the browser only what changed
(the plots of :mod:`.live_figures` and the panels that use them)."""

from __future__ import annotations

import numpy as np
from bokeh.models import ColumnDataSource


def set_range(r, start: float, end: float) -> None:
    """Give the ``Range1d`` ``r`` these bounds, sending nothing when it has them already.

    For axes the server sets: a range fitted in the browser (``DataRange1d``) is sent back
    to the server after each change of its data, one round trip each, and warns ("could
    not set initial ranges") while its plot has no data yet.
    """
    if (r.start, r.end) != (start, end):
        r.update(start=start, end=end)


def set_top(r, top: float, pad: float = 0.05) -> None:
    """:func:`set_range` from 0 to ``top`` and ``pad`` of it above (0 to 1 when ``top`` is
    not positive: nothing to show yet)."""
    set_range(r, 0.0, (1.0 + pad) * top if top > 0 else 1.0)


def replace_data(source: ColumnDataSource, data: dict) -> None:
    """Give ``source`` the columns ``data``, sending the browser only what changed.

    Columns already equal are not sent. Changed ones of the same length and dtype go as a
    *patch* into the source's own arrays (the glyphs redraw in place); otherwise the source
    gets a new ``data`` dict of copies (which later patches may overwrite without touching
    the caller's arrays, e.g. a cached result's). A new ``data`` dict also makes every
    legend whose items reach the source rebuild all its entries, each with a new canvas
    (with :func:`blank` sources, shear-5's first wave creates 37 canvases, not 347).
    """
    old = source.data
    if old.keys() == data.keys():
        changed = {k: v for k, v in data.items() if not _same(old[k], v)}
        if not changed:
            return
        if all(_numeric(old[k]) and old[k].flags.owndata and old[k].flags.writeable
               and isinstance(v, np.ndarray) and v.shape == old[k].shape
               and v.dtype == old[k].dtype for k, v in changed.items()):
            source.patch({k: [(slice(0, v.size), v)] for k, v in changed.items()})
            return
    source.data = {k: v.copy() if _numeric(v) else v for k, v in data.items()}


def blank(n: int, *names: str, **fixed) -> dict:
    """Source columns: ``names`` as ``n`` NaNs (nothing is drawn), beside ``fixed`` ones.

    A source that starts at its final length takes its first data as a patch
    (:func:`replace_data`). From empty, the new length changed the source and its view
    in the browser several times per update, and each change rebuilt every entry of the
    figure's legend (12 rebuilds of each band figure's legend in beam-2d's first
    discrepancy run, three canvases each).
    """
    columns = {k: np.array(v, dtype=float) for k, v in fixed.items()}
    columns.update({k: np.full(n, np.nan) for k in names})
    return columns


def _numeric(column) -> bool:
    """Whether ``column`` is a 1-D NumPy array of numbers (what a patch can overwrite)."""
    return isinstance(column, np.ndarray) and column.ndim == 1 and column.dtype.kind in "fiub"


def _same(a, b) -> bool:
    """Whether two columns hold the same values, NaN equal to NaN (a blank row, see
    :func:`blank`); a ragged column: the same lines."""
    if len(a) != len(b):
        return False
    try:
        a, b = np.asarray(a), np.asarray(b)
    except ValueError:                       # ragged (multi_line): compare line by line
        return all(_same(x, y) for x, y in zip(a, b))
    numeric = a.dtype.kind in "fc" and b.dtype.kind in "fc"
    return np.array_equal(a, b, equal_nan=numeric)
