"""The data of the History matching tab's plots, from the waves (pure functions)."""

from __future__ import annotations

import numpy as np
from bokeh.models import LinearColorMapper

from mdcore._validation import as_float_array, as_int, as_positive_float

from .history_model import HistoryModel
from .plots import THETA_MAP_COLOR, WAVE_COLORS

#: At most this many NROY samples of a wave are drawn.
MAX_POINTS = 1500
#: Histogram bins over a single parameter's prior box (p = 1).
BINS = 40
#: Most waves a history match can have (the upper bound of the Max waves control).
MAX_WAVES = HistoryModel.param.max_waves.bounds[1]


def wave_samples(wave, max_points: int = MAX_POINTS) -> np.ndarray:
    """At most ``max_points`` of a wave's NROY samples (n, p): a subset drawn with a seed of
    the wave's index, so a wave shows the same points whichever wave the player is at."""
    max_points = as_int(max_points, "max_points", 1)
    nroy = wave.nroy
    if nroy.shape[0] > max_points:
        rng = np.random.default_rng(wave.index)
        nroy = nroy[np.sort(rng.choice(nroy.shape[0], max_points, replace=False))]
    return nroy


def nroy_columns(waves, p: int, max_points: int = MAX_POINTS) -> dict:
    """The scatter data of waves (in order, later waves drawn on top): columns ``t0`` …
    ``t{p-1}`` (θ) and ``wave`` (index, coloured by :func:`wave_colors`)."""
    p = as_int(p, "p", 1)
    parts = [(w.index, wave_samples(w, max_points)) for w in waves]
    theta = np.concatenate([s for _, s in parts]) if parts else np.empty((0, p))
    index = np.concatenate([np.full(s.shape[0], k, np.int32) for k, s in parts]) if parts \
        else np.empty(0, np.int32)
    return {**{f"t{i}": theta[:, i] for i in range(p)}, "wave": index}


def histogram_columns(waves, bounds, bins: int = BINS) -> dict:
    """Per wave, the histogram (counts) of its NROY samples of a single parameter over the
    prior box: columns ``left``, ``right``, ``top``, ``wave`` (``bins`` rows a wave)."""
    bins = as_int(bins, "bins", 1)
    bounds = as_float_array(bounds, "bounds", ndim=2)
    if bounds.shape[1] != 2 or not bounds[0, 0] < bounds[0, 1]:
        raise ValueError(f"bounds must have rows (low, high) with low < high; received "
                         f"{bounds.tolist()}.")
    edges = np.linspace(bounds[0, 0], bounds[0, 1], bins + 1)
    cols: dict[str, list] = {"left": [], "right": [], "top": [], "wave": []}
    for w in waves:
        counts, _ = np.histogram(wave_samples(w)[:, 0], bins=edges)
        cols["left"] += list(edges[:-1])
        cols["right"] += list(edges[1:])
        cols["top"] += list(counts.astype(float))
        cols["wave"] += [w.index] * bins
    return {k: np.asarray(v, np.int32 if k == "wave" else float) for k, v in cols.items()}


def wave_colors() -> dict:
    """The colour of a row from its ``wave`` column, computed in the browser: wave k gets
    ``WAVE_COLORS[(k − 1) mod 10]`` (a palette of :data:`MAX_WAVES` colours over
    [0.5, MAX_WAVES + 0.5], one per integer). Sending colour names instead was a string
    per sample, half of a wave's message."""
    palette = [WAVE_COLORS[k % len(WAVE_COLORS)] for k in range(MAX_WAVES)]
    return {"field": "wave", "transform": LinearColorMapper(
        palette=palette, low=0.5, high=MAX_WAVES + 0.5)}


#: The rows of waves 1..``upto`` (CustomJSFilter code): the player moves ``upto`` only.
SHOWN_WAVES_JS = """
const w = source.data.wave;
const shown = new Array(w.length);
for (let i = 0; i < w.length; i++) shown[i] = w[i] <= upto;
return shown;
"""


def contour_lines(t1, t2, I, level: float) -> dict:
    """The contour of ``I`` (n2, n1) at ``level`` on the grid (t1, t2): columns ``xs``,
    ``ys`` (one list of points per line) for a ``multi_line`` glyph."""
    from contourpy import contour_generator
    t1, t2 = as_float_array(t1, "t1", ndim=1), as_float_array(t2, "t2", ndim=1)
    I = as_float_array(I, "I", ndim=2)
    if I.shape != (t2.size, t1.size):
        raise ValueError(f"I must have shape (len(t2), len(t1)) = ({t2.size}, {t1.size}); "
                         f"received {I.shape}.")
    level = as_positive_float(level, "level", "(the threshold T, e.g. 3)")
    if I.min() > level or I.max() < level:
        return {"xs": [], "ys": []}
    lines = contour_generator(t1, t2, I).lines(level)
    return {"xs": [ln[:, 0] for ln in lines], "ys": [ln[:, 1] for ln in lines]}


def variance_ratios(waves, n_out: int) -> np.ndarray:
    """(n_out, n_waves): the largest emulator variance at retained points ÷ (V_o + V_m)."""
    return np.array([[w.max_var[o] / w.var_threshold[o] for w in waves]
                     for o in range(n_out)], dtype=float).reshape(n_out, len(waves))


def padded(values, n: int) -> np.ndarray:
    """``values`` (1-D) followed by NaNs (not drawn) up to length ``n``, as floats. A
    non-finite value is kept (a ratio without a threshold is a gap in its line)."""
    n = as_int(n, "n", 0)
    values = as_float_array(values, "values", ndim=1, allow_empty=True, finite=False)
    if values.size > n:
        raise ValueError(f"values must have at most n = {n} entries; received {values.size}.")
    out = np.full(n, np.nan)
    out[:values.size] = values
    return out


def legend_html(waves, truth: bool, theta_map: bool, lines: bool = False) -> str:
    """A legend line: a swatch per wave shown, then the true θ and θ_MAP markers (a cross
    and a star, or for ``lines`` (p = 1) a dashed and a solid vertical line)."""
    items = [f'<span style="color:{WAVE_COLORS[(w.index - 1) % len(WAVE_COLORS)]}">■</span> '
             f"wave {w.index}" for w in waves]
    if truth:
        items.append("<b>┆</b> true θ" if lines else "<b>×</b> true θ")
    if theta_map:
        mark = "│" if lines else "★"
        items.append(f'<span style="color:{THETA_MAP_COLOR}"><b>{mark}</b></span> θ_MAP '
                     "(last wave)")
    return " &nbsp; ".join(items)
