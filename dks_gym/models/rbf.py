"""Multiquadric RBF interpolation in the parameter: the interpolant of the pDMD baseline (Eq. A3).

:class:`MultiquadricRBF` stands in for ezyrb's ``RBF(kernel="multiquadric")`` with the ``fit(points,
values)`` / ``predict(points)`` interface that PyDMD's ``ParametricDMD`` calls, so the pDMD baseline
does not need ezyrb (which installs Hugging Face ``datasets``, pyarrow and pandas). ezyrb's ``RBF`` is a
thin wrapper over ``scipy.interpolate.RBFInterpolator``; this is the same call with the same arguments,
so the predictions are the same numbers (tests/test_pdmd.py checks this against ezyrb):

* kernel "multiquadric", phi(r) = -sqrt(1 + (epsilon r)^2) in scipy's sign convention (the sign
  does not change the interpolant: the weights change sign with it);
* smoothing 0 (exact interpolation), all points as neighbours, scipy's default polynomial degree
  (0, a constant, for the multiquadric);
* ezyrb's default shape parameter, :func:`default_epsilon`.

``MultiquadricRBF(smoothing=s)`` departs from ezyrb on purpose: it adds ``s`` times :func:`kernel_scale` to
the diagonal of the kernel matrix (scipy's ``smoothing``), a ridge relative to the kernel's own scale
whatever the units and the spread of the parameter. The pDMD baseline needs it: with ezyrb's shape
parameter the kernel matrix of the 50 Burgers training viscosities has condition number ~3e18, so the
exact interpolant is a round-off-level solve whose predictions change with the BLAS build and thread count.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike
from scipy.interpolate import RBFInterpolator
from scipy.spatial.distance import pdist, squareform

import torch


def default_epsilon(points: ArrayLike) -> float:
    """ezyrb's default shape parameter for points (n, d): (prod of nonzero edges / d)^(1 / their count).

    The edges are those of the points' bounding box; d counts every dimension, a zero edge included,
    exactly as ezyrb 1.3 computes it. For one parameter this is the parameter range max - min.
    """
    xi = _points(points)
    edges = np.amax(xi, axis=0) - np.amin(xi, axis=0)
    edges = edges[np.nonzero(edges)]
    if edges.size == 0:
        raise ValueError("the interpolation points all coincide: no shape parameter can be derived from them")
    # The same numpy expression as ezyrb, so that epsilon (and every prediction) is bit for bit the same.
    return float(np.power(np.prod(edges) / xi.shape[-1], 1.0 / edges.size))


def kernel_scale(points: ArrayLike, epsilon: float) -> float:
    """The spectral norm of the multiquadric kernel matrix of ``points`` (n, d), doubly centered.

    The interpolant is a constant plus sum_i w_i phi(epsilon ||x - x_i||) with sum_i w_i = 0, so the
    kernel matrix K acts only on zero-sum weights: what matters is P K P with P = I - 11^T / n, not K,
    whose constant part can dominate. With ezyrb's epsilon and parameters spread over much less than one
    unit (the dambreak viscosities, range 0.08) K is within 1e-5 of all ones, and a ridge relative to its
    largest entry would drown the interpolant; relative to ||P K P||_2 it does not.
    """
    xi = _points(points)
    k = np.sqrt(1.0 + (epsilon * squareform(pdist(xi))) ** 2)
    k = k - k.mean(axis=0, keepdims=True)
    k = k - k.mean(axis=1, keepdims=True)
    return float(np.linalg.norm(k, 2)) if k.size else 0.0


def _points(points: ArrayLike) -> np.ndarray:
    """Points as a float (n, d) array; like scipy's RBFInterpolator, 1-D input is refused, not guessed."""
    xi = np.asarray(points, dtype=np.float64)
    if xi.ndim != 2:
        raise ValueError(f"points must be a 2-D array (n_points, n_dims), got shape {xi.shape}")
    return xi


class MultiquadricRBF:
    """Multiquadric radial-basis interpolant with ezyrb's default shape parameter.

    ``epsilon=None`` derives it from the points at every :meth:`fit`. (ezyrb derives it at its first fit
    and keeps it for later fits; ParametricDMD always refits on the same training parameters, so both
    give the same epsilon there.) ``smoothing`` (default 0: exact interpolation, as ezyrb) is relative to
    :func:`kernel_scale` of the points; :attr:`fitted_smoothing` is the absolute value handed to scipy.
    """

    kernel = "multiquadric"

    def __init__(self, epsilon: float | None = None, smoothing: float = 0.0) -> None:
        if epsilon is not None and not epsilon > 0:
            raise ValueError(f"epsilon must be positive, got {epsilon}")
        if not 0 <= smoothing < 1:
            raise ValueError(f"smoothing (relative to the kernel's scale) must be in [0, 1), got {smoothing}")
        self.epsilon = epsilon
        self.smoothing = float(smoothing)
        self.fitted_epsilon: float | None = None
        self.fitted_smoothing: float | None = None
        self.interpolator: RBFInterpolator | None = None

    def fit(self, points: ArrayLike, values: ArrayLike) -> "MultiquadricRBF":
        """Interpolate ``values`` (n, ...) given at ``points`` (n, d); real or complex values."""
        xi = _points(points)
        self.fitted_epsilon = default_epsilon(xi) if self.epsilon is None else float(self.epsilon)
        self.fitted_smoothing = 0.0
        if self.smoothing > 0:
            self.fitted_smoothing = self.smoothing * kernel_scale(xi, self.fitted_epsilon)
        self.interpolator = RBFInterpolator(
            xi, np.asarray(values), kernel=self.kernel, epsilon=self.fitted_epsilon,
            smoothing=self.fitted_smoothing, neighbors=None, degree=None,
        )
        return self

    def predict(self, points: ArrayLike) -> np.ndarray:
        """The interpolant at ``points`` (n_new, d), shape (n_new, ...)."""
        if self.interpolator is None:
            raise RuntimeError("this MultiquadricRBF is not fitted yet: call fit(points, values)")
        return self.interpolator(_points(points))


def cardinal_weights(points: ArrayLike, at: "torch.Tensor", smoothing: float = 0.0) -> "torch.Tensor":
    """The weights W (B, n) with which :class:`MultiquadricRBF` (ezyrb's epsilon, ``smoothing`` relative to
    :func:`kernel_scale`) fitted on ``points`` (n, 1) predicts any values V (n, ...) at the parameters ``at``
    (B,): prediction = W @ V, as a torch function of ``at`` (float64), so that it can be differentiated.

    The interpolant is linear in the values: W = [phi(eps |at - x_j|), 1] times the inverse of the bordered
    system scipy solves (the kernel -sqrt(1 + r^2) on eps-scaled distances, the ridge on its diagonal, the
    constant of degree 0)."""
    xi = _points(points)
    eps = default_epsilon(xi)
    ridge = smoothing * kernel_scale(xi, eps) if smoothing > 0 else 0.0
    x = torch.as_tensor(xi[:, 0], dtype=torch.float64, device=at.device)
    n = len(x)
    system = torch.zeros(n + 1, n + 1, dtype=torch.float64, device=at.device)
    system[:n, :n] = -torch.sqrt(1 + (eps * (x[:, None] - x[None, :])) ** 2)
    system[:n, :n] += ridge * torch.eye(n, dtype=torch.float64, device=at.device)
    system[:n, n] = system[n, :n] = 1.0
    row = torch.cat([-torch.sqrt(1 + (eps * (at[:, None] - x[None, :])) ** 2), at.new_ones(len(at), 1)], dim=1)
    return torch.linalg.solve(system, row.mT).mT[:, :n]  # the bordered system is symmetric
