"""The MLP latent map z_{k+1} = f(z_k, mu) acting on [z; s(mu)] (Appendix A.2)."""

from __future__ import annotations

import torch
from torch import nn


class MLPTransition(nn.Module):
    """Fully connected map [z; s] (2r) -> ``n_hidden`` hidden layers of ``width`` with GELU -> r.

    The paper's Table mlp_latent_hparams: 4 hidden layers of width 105, which at r = 32 gives
    6,825 + 3 * 11,130 + 3,392 = 43,607 parameters. The output is the next latent state itself
    (no residual connection; the paper describes none).
    """

    def __init__(self, r: int, width: int = 105, n_hidden: int = 4) -> None:
        super().__init__()
        layers: list[nn.Module] = [nn.Linear(2 * r, width), nn.GELU()]
        for _ in range(n_hidden - 1):
            layers += [nn.Linear(width, width), nn.GELU()]
        layers.append(nn.Linear(width, r))
        self.net = nn.Sequential(*layers)

    def forward(self, z: torch.Tensor, s: torch.Tensor) -> torch.Tensor:
        """(B, r) latent states and (B, r) embeddings -> (B, r) next latent states."""
        return self.net(torch.cat([z, s], dim=-1))
