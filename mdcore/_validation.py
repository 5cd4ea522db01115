"""Input checks of the public boundary: a ``ValueError`` names the argument, what was
expected, what was received and how to fix it."""

from __future__ import annotations

import numpy as np

#: Largest magnitude of an observation or input: the method squares values (variances,
#: kernels), which overflow float64 beyond it.
MAX_MAGNITUDE = 1e30
#: Largest seed: an int64, which any JSON reader and NumPy's seeding take as it is.
MAX_SEED = 2**63 - 1


def short(value, limit: int = 60) -> str:
    """``repr(value)``, cut in the middle when longer than ``limit`` characters."""
    text = repr(value)
    if len(text) <= limit:
        return text
    return f"{text[:limit // 2]}…{text[-10:]} ({len(text):,} characters)"


def as_float_array(value, name: str, *, ndim: int | None = None, min_ndim: int | None = None,
                   allow_empty: bool = False, finite: bool = True) -> np.ndarray:
    """``value`` as a float64 array named ``name``, with exactly ``ndim`` or at least
    ``min_ndim`` dimensions, non-empty unless ``allow_empty``, finite if ``finite``."""
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name} must be a numeric array; could not convert it ({exc}).") from None
    if ndim is not None and arr.ndim != ndim:
        raise ValueError(f"{name} must have {ndim} dimension(s); received shape {arr.shape}.")
    if min_ndim is not None and arr.ndim < min_ndim:
        raise ValueError(
            f"{name} must have at least {min_ndim} dimension(s); received shape {arr.shape}.")
    if not allow_empty and arr.size == 0:
        raise ValueError(f"{name} is empty (shape {arr.shape}); it needs at least one value.")
    if finite and not np.all(np.isfinite(arr)):
        bad = int(np.size(arr) - np.count_nonzero(np.isfinite(arr)))
        raise ValueError(
            f"{name} contains {bad} NaN or infinite value(s) (shape {arr.shape}); "
            "remove or impute them before calling.")
    return arr


def check_positive(arr: np.ndarray, name: str, *, strict: bool = True) -> np.ndarray:
    """Raise when ``arr`` has values that are negative (or zero, when ``strict``)."""
    bad = arr <= 0 if strict else arr < 0
    if np.any(bad):
        what = "positive" if strict else "non-negative"
        raise ValueError(
            f"{name} must be {what}; received minimum {float(np.min(arr))!r}. "
            f"Variances and thresholds are {what} numbers.")
    return arr


def as_int(value, name: str, minimum: int, maximum: int | None = None) -> int:
    """``value`` as an int (not a bool) in [``minimum``, ``maximum``]; ``maximum`` refuses a
    size such as ``10**12`` samples before the memory runs out."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < minimum:
        raise ValueError(f"{name} must be an integer ≥ {minimum}; received {value!r}.")
    if maximum is not None and value > maximum:
        raise ValueError(f"{name} must be an integer ≥ {minimum} and ≤ {maximum:,}; received "
                         f"{value!r}, which would need more memory and time than any machine "
                         f"has. Use a value up to {maximum:,}.")
    return int(value)


def as_number(value) -> float:
    """``float(value)``, or NaN for what is not a number (a bool included): the caller's
    range check then refuses it with its own message."""
    if isinstance(value, bool):
        return float("nan")
    try:
        return float(value)
    except (TypeError, ValueError):
        return float("nan")


def as_positive_float(value, name: str, hint: str = "") -> float:
    """A finite scalar > 0 as float; ``hint`` ends the message (meaning, a usual value)."""
    out = as_number(value)
    if not np.isfinite(out) or out <= 0:
        raise ValueError(f"{name} must be a positive number (finite, > 0); received "
                         f"{value!r}." + (f" {hint}" if hint else ""))
    return out


def check_bounds(bounds, name: str = "bounds") -> np.ndarray:
    """Check a (p, 2) array of [lower, upper] rows with lower < upper."""
    b = as_float_array(bounds, name, ndim=2)
    if b.shape[1] != 2:
        raise ValueError(f"{name} must have shape (p, 2) with [lower, upper] rows; "
                         f"received shape {b.shape}.")
    if np.any(b[:, 0] >= b[:, 1]):
        rows = np.nonzero(b[:, 0] >= b[:, 1])[0].tolist()
        raise ValueError(f"{name} needs lower < upper in every row; rows {rows} are not "
                         f"(received {b[rows].tolist()}).")
    return b


def choose(value: str, name: str, options) -> str:
    """Check that a string option is one of ``options`` (scipy-style message)."""
    try:
        known = value in options
    except TypeError:                        # unhashable (a list, a dict): not an option
        known = False
    if not known:
        raise ValueError(f"{value!r} is not a valid {name}. It must be one of {sorted(options)!r}.")
    return value


def check_type(value, kind, name: str, what: str):
    """``value`` if it is a ``kind``, else "``name`` must be ``what``; received <its type>"."""
    if not isinstance(value, kind):
        raise ValueError(f"{name} must be {what}; received {type(value).__name__}.")
    return value


def as_seed_int(seed, name: str = "seed") -> int:
    """An integer seed (for streams ``[seed, k]``) from an int ≥ 0 or a Generator, drawn from
    it so that the result is reproducible from the Generator's state."""
    if isinstance(seed, np.random.Generator):
        return int(seed.integers(0, MAX_SEED))
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or not \
            0 <= seed <= MAX_SEED:
        raise ValueError(f"{name} must be an integer from 0 to 2**63 − 1 or a "
                         f"numpy.random.Generator; received {short(seed)}. Any seed in that "
                         "range gives its own reproducible run, e.g. 0.")
    return int(seed)


def as_outputs(z, n_rows: int, name: str = "z") -> np.ndarray:
    """Observations as an (N, n_out) float array, one row per input: ``(N,)`` is one output."""
    arr = as_float_array(z, name, min_ndim=1)
    if arr.ndim == 1:
        arr = arr[:, None]
    if arr.ndim != 2 or arr.shape[0] != n_rows:
        raise ValueError(f"{name} must have shape (N, n_out) with N = {n_rows} rows like X "
                         f"(or (N,) for one output); received {arr.shape}.")
    if np.max(np.abs(arr), initial=0.0) > MAX_MAGNITUDE:
        raise ValueError(f"{name} has values up to {np.max(np.abs(arr)):.3g} in magnitude; "
                         f"they must be at most {MAX_MAGNITUDE:g}, or their squares (variances) "
                         "overflow. Express them in other units.")
    return arr


def as_log_params(log_params, d_y: int, d_x: int) -> np.ndarray:
    """GP log hyperparameters, shape (..., P) with P = 2 + d_y + d_x (docs/method.md §2 layout
    ``[log σ_f, log ℓ_y×d_y, log ℓ_x×d_x, log σ_n]``), as a finite float64 array."""
    lp = as_float_array(log_params, "log_params", min_ndim=1)
    P = 2 + d_y + d_x
    if lp.shape[-1] != P:
        raise ValueError(
            f"log_params must have last dimension P = 2 + d_y + d_x = 2 + {d_y} + {d_x} = {P} "
            f"([log σ_f, log ℓ_y×{d_y}, log ℓ_x×{d_x}, log σ_n]); received shape {lp.shape}.")
    return lp
