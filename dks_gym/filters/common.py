"""Shared pieces of the latent-space filters (paper Section II.E, SPEC section 4).

The filters never see a model, only callables over batched tensors (DAPPER style): a
:class:`LatentDynamics` bundles the forecast map ``f`` (Eq. 13), the observation map ``h``, and
optionally their Jacobians. Everything here carries a leading batch dimension ``B`` (many
environments or trajectories at once) and follows the dtype and device of the state it is given.

Conventions that hold for every function in :mod:`dks_gym.filters`:

- a latent mean is ``(B, r)``, a covariance ``(B, r, r)``, an ensemble ``(B, n, r)``, a measurement
  ``(B, m)``;
- a noise covariance (``Q``, ``R``, ``P0``) may be given as a scalar variance, a ``(B,)`` tensor of
  per-element variances, a ``(d, d)`` matrix shared by the batch, or a ``(B, d, d)`` stack (a
  diagonal covariance is passed as ``torch.diag(v)``: a 1-D tensor always means one variance per
  batch element);
- the callables act row by row: ``forecast(z)`` maps ``(N, r) -> (N, r)`` and ``observe(z)`` maps
  ``(N, r) -> (N, m)`` for ``N = k * B`` where each batch element owns ``k`` consecutive rows
  (``k = 1`` for the EKF, ``k = n`` members for the EnKF). :func:`bind_param` builds such a callable
  from a model function ``g(z, mu)`` and a per-element parameter ``mu`` of shape ``(B,)``. A callable
  that only accepts exactly ``B`` rows can set ``LatentDynamics(stacked_rows=False)``; the EnKF then
  calls it once per member.
"""

from __future__ import annotations

import math
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Literal

import torch
from torch import Tensor

Map = Callable[[Tensor], Tensor]
JacobianSpec = Map | Tensor | None
CovarianceSpec = float | Tensor
JacobianMethod = Literal["auto", "vmap", "loop"]
DivergencePolicy = Literal["raise", "reset"]


class FilterDivergence(RuntimeError):
    """Raised when a filter produces a non-finite mean or covariance (or a singular innovation covariance)."""


@dataclass(frozen=True)
class LatentDynamics:
    """The model as the filters see it: forecast ``f`` and observation ``h`` over batched latent states.

    ``forecast(z)``: ``(N, r) -> (N, r)``, the one-step latent map with the physical parameter already
    bound (Eq. 13). ``observe(z)``: ``(N, r) -> (N, m)``, the decoded sensor values ``S(G(z))``.
    ``forecast_jacobian`` / ``observe_jacobian``: ``None`` (autodiff), a callable ``z -> (B, r, r)`` /
    ``(B, m, r)``, or a constant tensor (``(r, r)`` or ``(B, r, r)``, e.g. the Koopman matrix ``K(mu)``;
    ``(m, r)`` or ``(B, m, r)``, e.g. pDMD's ``S U_r``); a callable ``observe_jacobian`` may also return the
    pair ``(h(z), J)`` when it computes the values on the way (the neural models' sensor-local Jacobian), which
    spares the filter a decode. ``stacked_rows``: whether the callables accept ``k * B`` rows (see the module
    docstring).
    """

    forecast: Map
    observe: Map
    forecast_jacobian: JacobianSpec = None
    observe_jacobian: JacobianSpec = None
    stacked_rows: bool = True

    def __post_init__(self) -> None:
        for name in ("forecast", "observe"):
            if not callable(getattr(self, name)):
                raise TypeError(
                    f"LatentDynamics.{name} must be a callable over (B, r) tensors, "
                    f"got {type(getattr(self, name)).__name__}"
                )
        for name in ("forecast_jacobian", "observe_jacobian"):
            value = getattr(self, name)
            if value is not None and not callable(value) and not isinstance(value, Tensor):
                raise TypeError(
                    f"LatentDynamics.{name} must be None (autodiff), a callable or a tensor, got {type(value).__name__}"
                )


def bind_param(fn: Callable[[Tensor, Tensor], Tensor], mu: Tensor) -> Map:
    """Bind a per-element parameter ``mu`` ``(B, ...)`` to ``fn(z, mu)`` so that it accepts ``k * B`` stacked rows.

    Row ``j`` of the argument belongs to batch element ``j // k``; ``mu`` is repeated accordingly.
    """
    batch = mu.shape[0]

    def bound(z: Tensor) -> Tensor:
        if z.shape[0] % batch != 0:
            raise ValueError(f"got {z.shape[0]} rows, not a multiple of the batch size {batch} that mu was bound with")
        return fn(z, mu.repeat_interleave(z.shape[0] // batch, dim=0))

    return bound


@dataclass
class GaussianState:
    """A batch of Gaussian beliefs: ``mean`` ``(B, r)`` and ``cov`` ``(B, r, r)``."""

    mean: Tensor
    cov: Tensor

    def __post_init__(self) -> None:
        if self.mean.ndim != 2:
            raise ValueError(
                f"mean must be (B, r), got shape {tuple(self.mean.shape)}; "
                "add a leading batch dimension (z[None]) for one system"
            )
        batch, r = self.mean.shape
        if self.cov.shape != (batch, r, r):
            raise ValueError(f"cov must be (B, r, r) = {(batch, r, r)} to match the mean, got {tuple(self.cov.shape)}")


# ---------------------------------------------------------------------------------------------- checks


def _element_list(mask: Tensor, limit: int = 20) -> str:
    idx = torch.nonzero(mask.reshape(-1)).reshape(-1).tolist()
    text = ", ".join(str(i) for i in idx[:limit])
    return f"[{text}{', ...' if len(idx) > limit else ''}]"


def symmetrize(P: Tensor) -> Tensor:
    """Return ``(P + P^T) / 2`` over the last two axes."""
    return 0.5 * (P + P.mT)


def _floating_like(value: Tensor | float, like: Tensor) -> Tensor:
    return torch.as_tensor(value, dtype=like.dtype, device=like.device)


def as_covariance(value: CovarianceSpec, batch: int, dim: int, like: Tensor, name: str) -> Tensor:
    """Expand a scalar, ``(B,)``, ``(d, d)`` or ``(B, d, d)`` covariance to ``(B, d, d)`` in ``like``'s dtype/device."""
    v = _floating_like(value, like)
    if v.ndim == 3:
        if v.shape != (batch, dim, dim):
            raise ValueError(f"{name} must be (B, {dim}, {dim}) = {(batch, dim, dim)}, got {tuple(v.shape)}")
        return v
    eye = torch.eye(dim, dtype=like.dtype, device=like.device)
    if v.ndim == 0:
        return (v * eye).expand(batch, dim, dim)
    if v.ndim == 1:
        if v.shape[0] != batch:
            raise ValueError(
                f"{name} given as a 1-D tensor must hold one variance per batch element, shape ({batch},), "
                f"got {tuple(v.shape)}; "
                f"pass a diagonal covariance as torch.diag(v)"
            )
        return v[:, None, None] * eye
    if v.ndim == 2:
        if v.shape != (dim, dim):
            raise ValueError(
                f"{name} must be ({dim}, {dim}) (or scalar, (B,), (B, {dim}, {dim})), got {tuple(v.shape)}"
            )
        return v.expand(batch, dim, dim)
    raise ValueError(f"{name} must be a scalar, (B,), ({dim}, {dim}) or (B, {dim}, {dim}); got shape {tuple(v.shape)}")


def check_covariance_spec(value: CovarianceSpec, name: str, *, definite: bool) -> None:
    """Check a covariance spec before its batch size is known: finite, symmetric, and PD (``definite``) or PSD."""
    v = torch.as_tensor(value)
    if not v.is_floating_point():
        v = v.double()
    if not torch.isfinite(v).all():
        raise ValueError(f"{name} contains NaN or inf")
    if v.ndim <= 1:
        bad = (v <= 0) if definite else (v < 0)
        if bad.any():
            need = "positive" if definite else "non-negative"
            raise ValueError(f"{name} must be {need}; got {v.tolist()}")
        return
    if v.ndim == 2:
        v = v[None]
    check_symmetric(v, name, definite=definite)


def check_symmetric(P: Tensor, name: str, *, definite: bool = True) -> None:
    """Raise ValueError naming the batch elements where ``P`` ``(B, d, d)`` is not symmetric positive (semi)definite."""
    if P.ndim != 3 or P.shape[-1] != P.shape[-2]:
        raise ValueError(f"{name} must be a stack of square matrices (B, d, d), got shape {tuple(P.shape)}")
    finite = torch.isfinite(P).flatten(1).all(1)
    if not finite.all():
        raise ValueError(f"{name} contains NaN or inf in batch elements {_element_list(~finite)}")
    # A user's A @ A.T is symmetric only to rounding; anything beyond sqrt(eps) is a genuinely asymmetric input.
    tol = math.sqrt(torch.finfo(P.dtype).eps)
    scale = P.abs().flatten(1).amax(1).clamp_min(torch.finfo(P.dtype).tiny)
    asym = (P - P.mT).abs().flatten(1).amax(1) > tol * scale
    if asym.any():
        raise ValueError(
            f"{name} is not symmetric in batch elements {_element_list(asym)}; "
            "pass (P + P.T) / 2 if the asymmetry is rounding"
        )
    Ps = symmetrize(P)
    if definite:
        _, info = torch.linalg.cholesky_ex(Ps)
        bad = info != 0
        what = "positive definite"
    else:
        lowest = torch.linalg.eigvalsh(Ps)[..., 0]
        bad = lowest < -tol * scale
        what = "positive semidefinite"
    if bad.any():
        raise ValueError(f"{name} is not {what} in batch elements {_element_list(bad)}")


def check_mask(mask: Tensor | None, y: Tensor) -> Tensor | None:
    """Validate a ``(B, m)`` boolean mask of the readings present (True) in ``y``; None when all are present.

    A missing reading's value is ignored (NaN is the convention); the update uses the rows that are present.
    """
    if mask is None:
        return None
    mask = torch.as_tensor(mask, device=y.device)
    if mask.dtype != torch.bool or tuple(mask.shape) != tuple(y.shape):
        raise ValueError(f"mask must be a boolean tensor shaped like y {tuple(y.shape)} (True = the reading is "
                         f"present), got {mask.dtype} {tuple(mask.shape)}")
    return None if bool(mask.all()) else mask


def mask_measurement(y: Tensor, mask: Tensor | None, R: Tensor) -> tuple[Tensor, Tensor]:
    """``y`` with the missing readings set to 0 and ``R`` ``(B, m, m)`` with their rows and columns replaced by
    those of the identity: with the observation Jacobian's (or the predicted readings') missing rows zeroed,
    the update is exactly the one with H and R reduced to the rows present (the gain's missing columns are 0)."""
    if mask is None:
        return y, R
    present = mask.to(R.dtype)
    keep = present[:, :, None] * present[:, None, :]
    return torch.where(mask, y, torch.zeros_like(y)), R * keep + torch.diag_embed(1.0 - present)


def check_measurement(y: Tensor, batch: int, m: int | None, like: Tensor, mask: Tensor | None = None) -> Tensor:
    """Validate a measurement ``(B, m)`` (shape, finite where ``mask`` says present, dimension ``m`` if known);
    return it in ``like``'s dtype."""
    y = torch.as_tensor(y)
    if y.ndim != 2 or y.shape[0] != batch:
        raise ValueError(f"measurement y must be (B, m) with B = {batch}, got shape {tuple(y.shape)}")
    if m is not None and y.shape[1] != m:
        raise ValueError(
            f"measurement dimension changed: expected m = {m} values per batch element "
            "(as before / as observe() returns), "
            f"got {y.shape[1]}; a filter's sensor layout is fixed, call reset() (or build a new filter) to change it"
        )
    mask = check_mask(mask, y)  # before it is used: a mask of the wrong shape or dtype gets its own message
    present = torch.isfinite(y) if mask is None else torch.isfinite(y) | ~mask
    finite = present.all(1)
    if not finite.all():
        raise ValueError(
            f"measurement y contains NaN or inf in batch elements {_element_list(~finite)}; "
            "pass mask=... (True where a reading is present) for missing readings, or repair them"
        )
    return y.to(dtype=like.dtype, device=like.device)


def nonfinite_elements(*tensors: Tensor) -> Tensor:
    """Boolean ``(B,)``: batch elements where any of the given tensors (leading dim ``B``) holds NaN or inf."""
    bad = torch.zeros(tensors[0].shape[0], dtype=torch.bool, device=tensors[0].device)
    for t in tensors:
        bad |= ~torch.isfinite(t).flatten(1).all(1)
    return bad


def raise_if_diverged(bad: Tensor, what: str) -> None:
    """Raise :class:`FilterDivergence` naming the batch elements flagged in ``bad``."""
    if bad.any():
        raise FilterDivergence(
            f"{what} produced a non-finite mean/covariance (or a singular innovation covariance) in batch elements "
            f"{_element_list(bad)}; check the model's forecast norm, enlarge Q or R, or use on_divergence='reset'"
        )


def cholesky_or_nan(S: Tensor) -> tuple[Tensor, Tensor]:
    """Cholesky factor of ``S`` ``(B, d, d)`` and a ``(B,)`` failure mask; failed factors are NaN, never silent."""
    L, info = torch.linalg.cholesky_ex(S)
    failed = info != 0
    if failed.any():
        L = torch.where(failed[:, None, None], torch.full_like(L, float("nan")), L)
    return L, failed


def psd_sqrt(Q: Tensor) -> Tensor:
    """A factor ``L`` with ``L L^T = Q`` for symmetric PSD ``Q`` ``(B, d, d)``: Cholesky, or eigh where singular."""
    L, info = torch.linalg.cholesky_ex(Q)
    singular = info != 0
    if singular.any():
        w, V = torch.linalg.eigh(Q[singular])
        L = L.clone()
        L[singular] = V * w.clamp_min(0).sqrt()[..., None, :]
    return L


def spectral_norm(M: Tensor) -> Tensor:
    """Largest singular value of each matrix in a ``(B, a, b)`` stack.

    The square root of the largest eigenvalue of the smaller Gram matrix: the same number as an SVD to a few
    units of round-off relative to it (only the small singular values lose accuracy in the Gram), 3-4x faster
    for the stacks the filters record every step (benchmarks/perf.py).
    """
    gram = M.mT @ M if M.shape[-1] <= M.shape[-2] else M @ M.mT
    return torch.linalg.eigvalsh(gram)[..., -1].clamp_min(0.0).sqrt()


# ------------------------------------------------------------------------------------------- Jacobians


_warned_fallback = False


def value_and_jacobian(fn: Map, z: Tensor, method: JacobianMethod = "auto") -> tuple[Tensor, Tensor]:
    """``fn(z)`` ``(B, o)`` and its per-element Jacobian ``(B, o, r)`` by reverse-mode autodiff, detached.

    ``fn`` acts row by row, so the Jacobian of ``sum_b fn(z)[b]`` with respect to ``z`` holds every
    element's Jacobian; the model is called once on the whole batch (its bound parameters stay aligned)
    and differentiated with ``o`` reverse passes (``torch.func.jacrev``, vectorized by vmap), i.e. only
    the ``o`` outputs are differentiated. ``method="loop"`` runs those passes one by one with
    ``torch.autograd.grad`` (for models whose ops lack vmap rules); ``"auto"`` falls back to it, once
    warned, when vmap fails.
    """
    global _warned_fallback
    z = z.detach()
    if method not in ("auto", "vmap", "loop"):
        raise ValueError(f"jacobian method must be 'auto', 'vmap' or 'loop', got {method!r}")
    if method in ("auto", "vmap"):

        def summed(x: Tensor) -> tuple[Tensor, Tensor]:
            out = fn(x)
            return out.sum(0), out

        try:
            jac, out = torch.func.jacrev(summed, has_aux=True)(z)
            return out.detach(), jac.movedim(1, 0).detach()
        except (RuntimeError, NotImplementedError) as err:
            if method == "vmap":
                raise
            if not _warned_fallback:
                warnings.warn(
                    f"vmap-based Jacobian failed ({err}); falling back to one autograd pass per output", stacklevel=2
                )
                _warned_fallback = True
    with torch.enable_grad():
        x = z.clone().requires_grad_(True)
        out = fn(x)
        rows = []
        for i in range(out.shape[1]):
            (g,) = torch.autograd.grad(out[:, i].sum(), x, retain_graph=i < out.shape[1] - 1, allow_unused=True)
            rows.append(torch.zeros_like(z) if g is None else g)
    return out.detach(), torch.stack(rows, dim=1).detach()


def _check_output(out: Tensor, shape: tuple[int, ...], what: str) -> Tensor:
    if tuple(out.shape) != shape:
        raise ValueError(f"{what} returned shape {tuple(out.shape)}, expected {shape}")
    return out


def _constant_jacobian(J: Tensor, batch: int, rows: int, r: int, like: Tensor, what: str) -> Tensor:
    J = J.to(dtype=like.dtype, device=like.device)
    if J.ndim == 2:
        J = J.expand(batch, *J.shape)
    if rows < 0:
        rows = J.shape[-2]
    return _check_output(J, (batch, rows, r), what)


def _with_jacobian(
    fn: Map, spec: JacobianSpec, z: Tensor, method: JacobianMethod, what: str, rows: int | None
) -> tuple[Tensor, Tensor]:
    """``fn(z)`` and its Jacobian at ``z`` ``(B, rows, r)``: from ``spec`` where the dynamics supply one (a
    tensor, or a callable of ``z``), by autodiff otherwise. ``rows`` None takes the row count from ``fn(z)``
    (the measurement count), falling back to the Jacobian's own when ``fn(z)`` is not ``(B, m)``."""
    batch, r = z.shape
    if spec is None:
        return value_and_jacobian(fn, z, method)
    with torch.no_grad():
        J = spec if isinstance(spec, Tensor) else spec(z)
        out, J = J if isinstance(J, tuple) else (fn(z), J)
    if rows is None:
        rows = out.shape[-1] if out.ndim == 2 else -1
    return out, _constant_jacobian(J, batch, rows, r, z, what)


def forecast_with_jacobian(
    dynamics: LatentDynamics, z: Tensor, method: JacobianMethod = "auto"
) -> tuple[Tensor, Tensor]:
    """``f(z)`` ``(B, r)`` and ``F = df/dz`` at ``z`` ``(B, r, r)`` (Eq. 14), however the dynamics supply it."""
    batch, r = z.shape
    z_next, F = _with_jacobian(dynamics.forecast, dynamics.forecast_jacobian, z, method, "forecast_jacobian", r)
    return _check_output(z_next, (batch, r), "forecast"), F


def observe_with_jacobian(
    dynamics: LatentDynamics, z: Tensor, method: JacobianMethod = "auto"
) -> tuple[Tensor, Tensor]:
    """``h(z)`` ``(B, m)`` and ``J = dh/dz`` at ``z`` ``(B, m, r)`` (Eqs. 15-16)."""
    y, J = _with_jacobian(dynamics.observe, dynamics.observe_jacobian, z, method, "observe_jacobian", None)
    if y.ndim != 2 or y.shape[0] != z.shape[0]:
        raise ValueError(f"observe returned shape {tuple(y.shape)}, expected (B, m) with B = {z.shape[0]}")
    return y, J


def apply_rows(fn: Map, ensemble: Tensor, stacked_rows: bool) -> Tensor:
    """Apply a row-wise map to an ensemble ``(B, n, r)`` -> ``(B, n, o)``: one stacked call, or one per member."""
    batch, n, r = ensemble.shape
    with torch.no_grad():
        if stacked_rows:
            out = fn(ensemble.reshape(batch * n, r))
            if out.ndim != 2 or out.shape[0] != batch * n:
                raise ValueError(
                    f"callable returned shape {tuple(out.shape)} for {batch * n} stacked rows; "
                    f"expected ({batch * n}, o)"
                )
            return out.reshape(batch, n, out.shape[-1])
        return torch.stack([fn(ensemble[:, i]) for i in range(n)], dim=1)


# --------------------------------------------------------------------------------------- diagnostics


@dataclass
class Diagnostics:
    """Per-step filter diagnostics (SPEC section 5): each list entry is one ``step`` call.

    ``forecast_norm`` ``(B,)``: ``||F_k||_2`` (EKF; NaN for the EnKF, which uses no Jacobian);
    ``gain_norm`` ``(B,)``: ``||K_k||_2`` (0 when the step did not assimilate); ``spread`` ``(B,)``:
    ``sqrt(tr P / r)`` after the step (EnKF: sample covariance); ``reset`` ``(B,)`` bool: elements
    restarted by ``on_divergence='reset'``; ``wall_time``: seconds for the step; ``assimilated``.
    """

    forecast_norm: list[Tensor] = field(default_factory=list)
    gain_norm: list[Tensor] = field(default_factory=list)
    spread: list[Tensor] = field(default_factory=list)
    reset: list[Tensor] = field(default_factory=list)
    wall_time: list[float] = field(default_factory=list)
    assimilated: list[bool] = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.wall_time)

    def stacked(self, name: str) -> Tensor:
        """One diagnostic over all steps: ``(T, B)`` per element, ``(T,)`` for ``wall_time``/``assimilated``."""
        values = getattr(self, name)
        if name in ("wall_time", "assimilated"):
            return torch.tensor(values)
        if not values:
            raise ValueError(f"no steps recorded yet for {name!r}")
        return torch.stack(values)

    @property
    def max_forecast_norm(self) -> Tensor:
        """``max_k ||F_k||_2`` per batch element (the paper's operator-norm table)."""
        return self.stacked("forecast_norm").amax(0)

    @property
    def mean_wall_time(self) -> float:
        """Average seconds per step."""
        return sum(self.wall_time) / max(len(self.wall_time), 1)

    def as_dict(self) -> dict[str, list]:
        """Plain lists (JSON-ready): per-element diagnostics as ``[T][B]`` nested lists."""
        out: dict[str, list] = {"wall_time": list(self.wall_time), "assimilated": list(self.assimilated)}
        for name in ("forecast_norm", "gain_norm", "spread", "reset"):
            values = getattr(self, name)
            out[name] = torch.stack(values).cpu().tolist() if values else []
        return out


class StepTimer:
    """Wall-clock time of one filter step, synchronizing CUDA so that queued kernels are counted."""

    def __init__(self, device: torch.device) -> None:
        self.device = device

    def __enter__(self) -> StepTimer:
        self._start = time.perf_counter()
        return self

    def __exit__(self, *exc: object) -> None:
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)
        self.seconds = time.perf_counter() - self._start


class SequentialFilter:
    """What the :class:`~dks_gym.filters.EKF` and :class:`~dks_gym.filters.EnKF` classes share.

    Holds the dynamics and noise specs, validates measurements (fixed dimension ``m`` between resets),
    applies the divergence policy, and records :class:`Diagnostics`.
    """

    def __init__(
        self,
        dynamics: LatentDynamics,
        *,
        R: CovarianceSpec | None,
        sigma: float | Tensor | None,
        Q: CovarianceSpec,
        on_divergence: DivergencePolicy,
        record_diagnostics: bool,
    ) -> None:
        if not isinstance(dynamics, LatentDynamics):
            raise TypeError(f"dynamics must be a LatentDynamics, got {type(dynamics).__name__}")
        if (R is None) == (sigma is None):
            raise ValueError(
                "give exactly one of R (measurement-noise covariance) or sigma (its standard deviation, R = sigma^2 I)"
            )
        if sigma is not None:
            if torch.as_tensor(sigma).ndim > 1:
                raise ValueError(
                    f"sigma must be a scalar or (B,), got shape {tuple(torch.as_tensor(sigma).shape)}; "
                    "pass a full covariance as R"
                )
            check_covariance_spec(sigma, "sigma", definite=True)
        else:
            check_covariance_spec(R, "R", definite=True)
        check_covariance_spec(Q, "Q", definite=False)
        if on_divergence not in ("raise", "reset"):
            raise ValueError(f"on_divergence must be 'raise' or 'reset', got {on_divergence!r}")
        self.dynamics = dynamics
        self.R = R
        self.sigma = sigma
        self.Q = Q
        self.on_divergence = on_divergence
        self.record_diagnostics = record_diagnostics
        self.diagnostics = Diagnostics()
        self.n_steps = 0
        self._m: int | None = None
        self._batch: int | None = None

    def _require_reset(self) -> None:
        if self._batch is None:
            raise RuntimeError(f"{type(self).__name__}.reset(z0, P0) must be called before step()")

    def _start(self, z0: Tensor) -> tuple[int, int]:
        z0 = torch.as_tensor(z0)
        if z0.ndim != 2:
            raise ValueError(
                f"z0 must be (B, r), got shape {tuple(z0.shape)}; "
                "add a leading batch dimension (z0[None]) for one system"
            )
        if not z0.is_floating_point():
            raise ValueError(f"z0 must be a float32/float64 tensor, got {z0.dtype}")
        if not torch.isfinite(z0).all():
            raise ValueError(f"z0 contains NaN or inf in batch elements {_element_list(~torch.isfinite(z0).all(1))}")
        self._batch, r = z0.shape
        self._m = None
        self._Q_key = self._R_key = None
        self.n_steps = 0
        self.diagnostics = Diagnostics()
        return self._batch, r

    def _initial_covariance(self, P0: CovarianceSpec | None, z0: Tensor) -> Tensor:
        batch, r = z0.shape
        P = as_covariance(1.0 if P0 is None else P0, batch, r, like=z0, name="P0")
        check_symmetric(P, "P0", definite=True)
        return symmetrize(P).clone()

    def _process_noise(self, like: Tensor) -> Tensor:
        """``Q`` as ``(B, r, r)`` on the state's dtype/device (built in that dtype, so float64 stays exact)."""
        key = (like.dtype, like.device)
        if getattr(self, "_Q_key", None) != key:
            self._Q_cache = as_covariance(self.Q, self._batch, like.shape[-1], like=like, name="Q")
            self._Q_key = key
        return self._Q_cache

    def _measurement_noise(self, like: Tensor, m: int) -> Tensor:
        """``R`` as ``(B, m, m)`` on the state's dtype/device (``sigma^2 I`` when built from ``sigma``)."""
        key = (like.dtype, like.device, m)
        if getattr(self, "_R_key", None) != key:
            if self.sigma is not None:
                R = as_covariance(_floating_like(self.sigma, like) ** 2, self._batch, m, like=like, name="sigma")
            else:
                R = as_covariance(self.R, self._batch, m, like=like, name="R")
            self._R_cache, self._R_key = R, key
        return self._R_cache

    def _measurement(self, y: Tensor | None, like: Tensor, mask: Tensor | None = None) -> tuple[Tensor, Tensor | None]:
        """The checked measurement and mask (None: every reading present)."""
        if y is None:
            raise ValueError(
                "step(y, assimilate=True) needs a measurement y of shape (B, m); "
                "use step(assimilate=False) for a forward run"
            )
        if mask is not None:
            mask = torch.as_tensor(mask, device=like.device)
        y = check_measurement(y, self._batch, self._m, like, mask)
        return y, check_mask(mask, y)

    def _resolve_divergence(self, bad: Tensor, what: str) -> None:
        """Raise :class:`FilterDivergence` for the flagged elements unless the policy is ``'reset'``."""
        if self.on_divergence == "raise":
            raise_if_diverged(bad, f"{type(self).__name__} step {self.n_steps + 1} ({what})")

    def _record(
        self,
        timer: StepTimer,
        *,
        forecast_norm: Tensor,
        gain_norm: Tensor,
        spread: Tensor,
        reset: Tensor,
        assimilated: bool,
    ) -> None:
        if self.record_diagnostics:
            d = self.diagnostics
            d.forecast_norm.append(forecast_norm.detach())
            d.gain_norm.append(gain_norm.detach())
            d.spread.append(spread.detach())
            d.reset.append(reset.detach())
            d.wall_time.append(timer.seconds)
            d.assimilated.append(assimilated)
