"""Covariances as the filters take them: a spec expanded to ``(B, d, d)``, checked, symmetrized, factorized.

A spec (``Q``, ``R``, ``P0``) is a scalar variance, a ``(B,)`` tensor of per-element variances, a ``(d, d)``
matrix shared by the batch, or a ``(B, d, d)`` stack (a diagonal covariance is ``torch.diag(v)``).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from .batch_elements import element_list

CovarianceSpec = float | Tensor


def symmetrize(P: Tensor) -> Tensor:
    """Return ``(P + P^T) / 2`` over the last two axes (a new tensor; ``P`` is not modified)."""
    return (P + P.mT).mul_(0.5)  # halving in place: the same numbers as 0.5 * (...) without a second buffer


def floating_like(value: Tensor | float, like: Tensor) -> Tensor:
    """``value`` as a tensor in ``like``'s (floating) dtype and on its device."""
    return torch.as_tensor(value, dtype=like.dtype, device=like.device)


def as_covariance(value: CovarianceSpec, batch: int, dim: int, like: Tensor, name: str) -> Tensor:
    """Expand a scalar, ``(B,)``, ``(d, d)`` or ``(B, d, d)`` covariance to ``(B, d, d)`` in ``like``'s dtype/device."""
    v = floating_like(value, like)
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
        raise ValueError(f"{name} contains NaN or inf in batch elements {element_list(~finite)}")
    # A user's A @ A.T is symmetric only to rounding; anything beyond sqrt(eps) is a genuinely asymmetric input.
    tol = math.sqrt(torch.finfo(P.dtype).eps)
    scale = P.abs().flatten(1).amax(1).clamp_min(torch.finfo(P.dtype).tiny)
    asym = (P - P.mT).abs().flatten(1).amax(1) > tol * scale
    if asym.any():
        raise ValueError(
            f"{name} is not symmetric in batch elements {element_list(asym)}; "
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
        raise ValueError(f"{name} is not {what} in batch elements {element_list(bad)}")


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
