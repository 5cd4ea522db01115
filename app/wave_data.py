"""The data of the History matching tab's plots, from the waves (pure functions)."""

from __future__ import annotations

import numpy as np
from bokeh.models import LinearColorMapper

from .history_model import HistoryModel
from .plots import THETA_MAP_COLOR, WAVE_COLORS

#: At most this many NROY samples of a wave are drawn.
MAX_POINTS = 1500
#: Histogram bins over a single parameter's prior box (p = 1).
BINS = 40
#: Colour of the words saying that the true θ is ruled out.
RULED_OUT_COLOR = "#b00020"
#: Most waves a history match can have (the upper bound of the Max waves control).
MAX_WAVES = HistoryModel.param.max_waves.bounds[1]


def wave_samples(wave, max_points: int = MAX_POINTS) -> np.ndarray:
    """At most ``max_points`` of a wave's NROY samples (n, p): a subset drawn with a seed of
    the wave's index, so a wave shows the same points whichever wave the player is at."""
    nroy = wave.nroy
    if nroy.shape[0] > max_points:
        rng = np.random.default_rng(wave.index)
        nroy = nroy[np.sort(rng.choice(nroy.shape[0], max_points, replace=False))]
    return nroy


def nroy_columns(waves, p: int, max_points: int = MAX_POINTS) -> dict:
    """The scatter data of waves (in order, later waves drawn on top): columns ``t0`` …
    ``t{p-1}`` (θ) and ``wave`` (index, coloured by :func:`wave_colors`)."""
    parts = [(w.index, wave_samples(w, max_points)) for w in waves]
    theta = np.concatenate([s for _, s in parts]) if parts else np.empty((0, p))
    index = np.concatenate([np.full(s.shape[0], k, np.int32) for k, s in parts]) if parts \
        else np.empty(0, np.int32)
    return {**{f"t{i}": theta[:, i] for i in range(p)}, "wave": index}


def histogram_columns(waves, bounds, bins: int = BINS) -> dict:
    """Per wave, the histogram (counts) of its NROY samples of a single parameter over the
    prior box: columns ``left``, ``right``, ``top``, ``wave`` (``bins`` rows a wave)."""
    edges = np.linspace(*bounds[0], bins + 1)
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
    if I.min() > level or I.max() < level:
        return {"xs": [], "ys": []}
    lines = contour_generator(t1, t2, I).lines(level)
    return {"xs": [ln[:, 0] for ln in lines], "ys": [ln[:, 1] for ln in lines]}


def variance_ratios(waves, n_out: int) -> np.ndarray:
    """(n_out, n_waves): the largest emulator variance at retained points ÷ (V_o + V_m)."""
    return np.array([[w.max_var[o] / w.var_threshold[o] for w in waves]
                     for o in range(n_out)], dtype=float).reshape(n_out, len(waves))


def padded(values, n: int) -> np.ndarray:
    """``values`` (at most ``n``) followed by NaNs (not drawn) up to length ``n``."""
    out = np.full(n, np.nan)
    out[:len(values)] = values
    return out


def decades(lo: float, hi: float) -> tuple[float, float]:
    """The log axis ``[lo, hi]`` (both > 0) widened to whole powers of ten, two decades at
    least: over less, BokehJS's log ticker labels 1, 2, 3 … 6 within a few pixels (the
    emulator-variance plot of one wave)."""
    start = 10.0 ** np.floor(np.log10(lo))
    return start, max(10.0 ** np.ceil(np.log10(hi)), 100.0 * start)


def truth_verdict(waves, theta_true) -> tuple[bool, str]:
    r"""Whether ``theta_true`` (p,) is non-implausible after ``waves`` (mdcore ``Wave``\ s,
    in order): inside the prior box and at most the cutoff in every wave (Eq. 16), and
    that in words, with the implausibility that decides it.

    Beside NROY's edge the cross can sit on the last wave's points while being just
    outside (beam-1d at V_m = 0.014 mm²): the class needs the number, not only the picture.
    """
    problem = waves[0].problem
    t = np.asarray(theta_true, float).reshape(1, -1)
    b, cut = problem.bounds, problem.cutoff
    if not np.all((t[0] >= b[:, 0]) & (t[0] <= b[:, 1])):
        return False, "outside the prior box"
    largest = 0.0
    for w in waves:
        value = float(w.combined_implausibility(t)[0])
        if not value <= cut:
            return False, (f"ruled out at wave {w.index} (implausibility {value:.3g} > "
                           f"{cut:.3g})")
        largest = max(largest, value)
    return True, f"non-implausible (implausibility ≤ {largest:.3g} ≤ {cut:.3g})"


def legend_html(waves, truth: bool | tuple[bool, str], theta_map: bool,
                lines: bool = False) -> str:
    """A legend line: a swatch per wave shown, then the true θ and θ_MAP markers (a cross
    and a star, or for ``lines`` (p = 1) a dashed and a solid vertical line). ``truth``:
    whether to name the true θ, or :func:`truth_verdict`'s answer to say it too (in red
    when the truth is ruled out)."""
    items = [f'<span style="color:{WAVE_COLORS[(w.index - 1) % len(WAVE_COLORS)]}">■</span> '
             f"wave {w.index}" for w in waves]
    if truth:
        item = "<b>┆</b> true θ" if lines else "<b>×</b> true θ"
        if isinstance(truth, tuple):
            inside, words = truth
            item += f": {words}" if inside else \
                f': <b style="color:{RULED_OUT_COLOR}">{words}</b>'
        items.append(item)
    if theta_map:
        mark = "│" if lines else "★"
        items.append(f'<span style="color:{THETA_MAP_COLOR}"><b>{mark}</b></span> θ_MAP '
                     "(last wave)")
    return " &nbsp; ".join(items)
