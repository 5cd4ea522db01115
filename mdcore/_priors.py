"""Independent Gaussian priors (``N(mean, var)``, var a variance as in docs/method.md §7).

:class:`GaussianPrior` is over the log-φ vector of docs/method.md §2; :class:`ThetaPrior` is
over θ in the parameters' units, truncated to the emulator's box (KOH, docs/method.md §7).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ._validation import as_float_array, as_int


@dataclass(frozen=True)
class _DiagonalGaussian:
    """Independent Gaussian densities and draws for the two prior types."""

    mean: np.ndarray
    var: np.ndarray

    def _check(self, what: str, advice: str) -> None:
        mean = as_float_array(self.mean, f"{what} mean", ndim=1)
        var = as_float_array(self.var, f"{what} var", ndim=1)
        if mean.shape != var.shape:
            raise ValueError(f"{what} mean and var must have the same shape (P,); received "
                             f"{mean.shape} and {var.shape}.")
        if np.any(var <= 0):
            raise ValueError(f"{what} var must be positive; received {var.tolist()}. {advice}")
        object.__setattr__(self, "mean", mean)
        object.__setattr__(self, "var", var)

    @property
    def size(self) -> int:
        return self.mean.size

    def logpdf(self, x) -> np.ndarray:
        """Log density at ``x`` of shape (..., P); returns shape (...)."""
        d = np.asarray(x, dtype=np.float64) - self.mean
        return -0.5 * np.sum(d * d / self.var + np.log(2.0 * np.pi * self.var), axis=-1)

    def grad(self, x) -> np.ndarray:
        """Gradient of :meth:`logpdf`, shape (..., P)."""
        return -(np.asarray(x, dtype=np.float64) - self.mean) / self.var

    def sample(self, n: int, seed=None) -> np.ndarray:
        """Draw ``n`` samples, shape (n, P), from ``default_rng(seed)``."""
        n = as_int(n, "n", 1)
        rng = np.random.default_rng(seed)
        return self.mean + np.sqrt(self.var) * rng.standard_normal((n, self.size))


@dataclass(frozen=True)
class GaussianPrior(_DiagonalGaussian):
    """Independent Gaussian prior on the log hyperparameter vector (docs/method.md §2 layout).

    Parameters
    ----------
    mean, var : ndarray of shape (P,)
        Prior means and variances of the log hyperparameters.

    Examples
    --------
    >>> GaussianPrior(mean=[0.0, 0.0, 0.0, -3.0], var=[1.0, 1.0, 1.0, 1.0]).sample(2, seed=0).shape
    (2, 4)
    """

    def __post_init__(self):
        self._check("prior", "Use a small positive variance for a nearly fixed "
                             "hyperparameter.")


@dataclass(frozen=True)
class ThetaPrior(_DiagonalGaussian):
    """Gaussian prior of the calibration parameters θ, in their own units (docs/method.md §7).

    Parameters
    ----------
    mean, var : ndarray of shape (p,)
        Prior means in the parameters' units and variances in the units squared.
    """

    def __post_init__(self):
        self._check("theta_prior", "Give a variance per parameter, in its units squared.")

    def sample_in(self, bounds, n: int, seed=None) -> np.ndarray:
        """``n`` draws of the prior restricted to the box ``bounds`` (p, 2), by rejection; a
        ValueError if the prior has almost no mass in the box (nothing accepted in 20 rounds)."""
        b = as_float_array(bounds, "bounds", ndim=2)
        if b.shape != (self.size, 2):
            raise ValueError(f"bounds must have shape (p, 2) = ({self.size}, 2), one row per "
                             f"prior mean; received {b.shape}.")
        n = as_int(n, "n", 1)
        rng = np.random.default_rng(seed)
        out: list[np.ndarray] = []                     # one entry per round
        while sum(len(o) for o in out) < n:
            draw = self.sample(max(4 * n, 1000), seed=rng)
            out.append(draw[np.all((draw >= b[:, 0]) & (draw <= b[:, 1]), axis=1)])
            if len(out) == 20 and not any(len(o) for o in out):
                raise ValueError(f"the θ prior (mean {self.mean.tolist()}, var "
                                 f"{self.var.tolist()}) has almost no mass inside bounds "
                                 f"{b.tolist()}; centre the prior inside the box.")
        return np.concatenate(out)[:n]
