"""The learned parameter embedding s = e_omega(mu) of Eq. 6."""

from __future__ import annotations

import torch
from torch import nn


class ParameterEmbedding(nn.Module):
    """e_omega(mu): Linear(1, r) followed by ``n_hidden`` Linear(r, r) layers, GELU in between (Eq. 6).

    At r = 32 it has 64 + 4 * 1056 = 4,288 parameters. The raw parameter is first mapped affinely to
    [-1, 1] over ``param_range`` (buffers, no parameters) so that a Reynolds number of 990 and a
    viscosity of 0.01 reach the first layer on the same scale; the paper does not state its scaling.
    """

    def __init__(self, r: int, param_range: tuple[float, float], n_hidden: int = 4) -> None:
        super().__init__()
        low, high = (float(v) for v in param_range)
        if not high > low:
            raise ValueError(f"param_range must be (low, high) with high > low, got {param_range}")
        self.register_buffer("param_center", torch.tensor(0.5 * (low + high)))
        self.register_buffer("param_half_width", torch.tensor(0.5 * (high - low)))
        layers: list[nn.Module] = [nn.Linear(1, r)]
        for _ in range(n_hidden):
            layers += [nn.GELU(), nn.Linear(r, r)]
        self.net = nn.Sequential(*layers)

    def forward(self, mu: torch.Tensor) -> torch.Tensor:
        """(B,) physical parameter values -> (B, r) embedding."""
        mu_scaled = (mu.to(self.param_center.dtype) - self.param_center) / self.param_half_width
        return self.net(mu_scaled[:, None].to(self.net[0].weight.dtype))
