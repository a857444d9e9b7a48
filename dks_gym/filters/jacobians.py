"""The values and Jacobians of the forecast and observation maps: supplied by the model, or by autodiff."""

from __future__ import annotations

import warnings
from typing import Literal

import torch
from torch import Tensor

from .dynamics import JacobianSpec, LatentDynamics, Map

JacobianMethod = Literal["auto", "vmap", "loop"]

# The vmap fallback is announced once per process, not at every filter step.
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
