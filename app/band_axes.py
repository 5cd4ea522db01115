"""The axes of the Discrepancy tab's band plots, shared by the methods (as the paper's
panels are) and fixed to hold the widest band."""

from __future__ import annotations

import numpy as np

#: The axes of a band plot hold mean ± this many sd (the widest band offered), so a new
#: band redraws only the band: the axes, and the plot's layout, stay put.
WIDEST_BAND = 3
#: Margin around the data of a plot, as a fraction of its span.
PAD = 0.05


def band_extent(grid, c, truth, key, held: dict) -> tuple[tuple[float, float], tuple[float, float]]:
    """x and y extents of the Discrepancy tab's cell ``key`` of case ``c`` over the ``held``
    results (shown or hidden, :meth:`ExplorerState.held_results`) at the widest band, with
    the data (z) or the true δ (``truth`` on ``grid``, or None): fixed axes, so that
    neither a new band nor hiding a method rescales them, and a narrower band looks
    narrower."""
    xs, ys = [grid[:, 0]], []
    for result in held.values():
        on_grid = result.on_extra
        if c.d_x == 2:
            mean, var = on_grid.delta_mean[:, 0], on_grid.delta_var[:, 0]
        else:
            o, q = key
            mean, var = ((on_grid.z_mean[:, o], on_grid.z_var[:, o]) if q == "z"
                         else (on_grid.delta_mean[:, o], on_grid.delta_var[:, o]))
        sd = WIDEST_BAND * np.sqrt(np.maximum(var, 0.0))
        ys += [mean - sd, mean + sd]
    if c.d_x == 1 and key[1] == "z":
        xs += [c.X_train[:, 0], c.X_test[:, 0]]
        ys += [c.z_train[:, key[0]], c.z_test[:, key[0]]]
    elif truth is not None:                # a δ plot or the beam-2d slice
        ys.append(truth[:, 0 if c.d_x == 2 else key[0]])

    def padded(parts):
        lo = float(min(np.min(p) for p in parts))
        hi = float(max(np.max(p) for p in parts))
        pad = PAD * (hi - lo) if hi > lo else max(abs(lo), 1.0) * PAD
        return lo - pad, hi + pad

    return padded(xs), padded(ys)
