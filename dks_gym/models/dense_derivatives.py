"""Derivatives of the decoders' dense layers (Linear layers and exact GELUs), by the chain rule by hand.

The EKF's sensor Jacobian (:meth:`~dks_gym.models.backbones.ConvDecoder.sensor_jacobian`) carries the
convolutional part by autodiff over small windows and the dense part here; the predictive std
(:mod:`~dks_gym.models.decoder_variance`) pushes tangents through the same layers with :func:`gelu_slopes`.
"""

from __future__ import annotations

import math

import torch
from torch import nn


def gelu_slope(h: torch.Tensor) -> torch.Tensor:
    """The derivative of the exact GELU at ``h``: ``Phi(h) + h phi(h)``, detached (the linearization's
    constant; no gradient flows through it)."""
    with torch.no_grad():  # in place after the first product: two tensors allocated rather than ten
        tail = torch.mul(h, -0.5).mul_(h).exp_().mul_(h).div_(math.sqrt(2 * math.pi))  # h phi(h)
        return torch.div(h, math.sqrt(2)).erf_().add_(1).mul_(0.5).add_(tail)


def fc_jacobian(layers: nn.Sequential, x: torch.Tensor) -> torch.Tensor:
    """d layers(x) / dx per row, (N, out, in), for a stack of Linear layers and exact GELUs (the chain rule by
    hand, carried transposed so that each Linear is one matrix product over all rows: forward-mode autodiff
    through vmap costs several times more here)."""
    with torch.no_grad():
        slopes = iter(gelu_slopes(layers, x)[0])
        jac_t = torch.eye(x.shape[1], dtype=x.dtype, device=x.device)  # (in, features), shared until the first GELU
        for layer in layers:
            jac_t = jac_t @ layer.weight.T if isinstance(layer, nn.Linear) else jac_t * next(slopes)[:, None, :]
    jac_t = jac_t.expand(x.shape[0], -1, -1) if jac_t.ndim == 2 else jac_t
    return jac_t.mT


def fc_vjp(layers: nn.Sequential, x: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """``v @ d layers(x) / dx`` per row, ``v`` (N, m, out) -> (N, m, in), for the layers of
    :func:`fc_jacobian`: the chain rule from the output back, so the ``m`` rows of ``v`` pass each layer
    instead of the ``in`` columns of the Jacobian (fewer numbers where ``m < in``: 16 sensors against r = 32)."""
    with torch.no_grad():
        slopes = gelu_slopes(layers, x)[0]
        for layer in reversed(layers):
            v = v @ layer.weight if isinstance(layer, nn.Linear) else v * slopes.pop()[:, None, :]
    return v


def gelu_slopes(layers: nn.Sequential, x: torch.Tensor) -> tuple[list[torch.Tensor], torch.Tensor]:
    """The forward pass of ``layers`` at ``x`` (N, in): the slope at each GELU's input (N, features), in layer
    order, and the output. TypeError for a layer other than a Linear or an exact GELU (no rule for it)."""
    slopes, h = [], x
    for layer in layers:
        if isinstance(layer, nn.GELU) and layer.approximate == "none":
            slopes.append(gelu_slope(h))
        elif not isinstance(layer, nn.Linear):
            raise TypeError(f"no Jacobian rule for {type(layer).__name__} in the decoder's dense layers")
        h = layer(h)
    return slopes, h


__all__ = ["fc_jacobian", "fc_vjp", "gelu_slope", "gelu_slopes"]
