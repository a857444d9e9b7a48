"""The Koopman latent map: K(mu; dt) = exp(A(mu) dt) with A = Q - Q^T - diag(d * d) (Eqs. 7-9)."""

from __future__ import annotations

import torch
from torch import nn


def _generator_mlp(r: int, n_out: int, n_hidden: int) -> nn.Sequential:
    """``n_hidden`` hidden layers of width r with GELU, a linear output, LayerNorm without affine."""
    layers: list[nn.Module] = []
    for _ in range(n_hidden):
        layers += [nn.Linear(r, r), nn.GELU()]
    layers += [nn.Linear(r, n_out), nn.LayerNorm(n_out, elementwise_affine=False)]
    return nn.Sequential(*layers)


def dissipative_generator(q: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
    """A = Q - Q^T - diag(d * d) from (B, r, r) and (B, r) (Eq. 9): skew part plus a non-positive diagonal."""
    return q - q.transpose(-1, -2) - torch.diag_embed(d * d)


class KoopmanOperator(nn.Module):
    """Parameter-dependent linear latent map z_{k+1} = K(mu; dt) z_k (Eq. 7).

    Q_theta: R^r -> R^{r^2} and d_theta: R^r -> R^r act on the embedding s = e(mu) (Table
    koopman_mlp_hparams); at r = 32 they have 38,016 + 5,280 = 43,296 parameters. A has a skew-symmetric
    part and a diagonal <= 0, so ||K||_2 <= 1 (non-expansive) for any weights. The matrix exponential is
    evaluated in float64 and cast back, so that rounding does not push ||K||_2 above 1 by more than ~1e-7.
    """

    def __init__(self, r: int, dt: float, n_hidden: int = 4) -> None:
        super().__init__()
        if not dt > 0:
            raise ValueError(f"dt must be positive, got {dt}")
        self.r = r
        self.dt = float(dt)
        self.q_net = _generator_mlp(r, r * r, n_hidden)  # Q_theta (Eq. 8)
        self.d_net = _generator_mlp(r, r, n_hidden)  # d_theta (Eq. 8)

    def generator(self, s: torch.Tensor) -> torch.Tensor:
        """A(mu) (B, r, r) from the embedding s (B, r) (Eq. 9)."""
        q = self.q_net(s).view(-1, self.r, self.r)
        return dissipative_generator(q, self.d_net(s))

    def operator(self, s: torch.Tensor) -> torch.Tensor:
        """K(mu; dt) = exp(A(mu) dt) (B, r, r) (Eq. 7)."""
        a = self.generator(s)
        return torch.linalg.matrix_exp(a.double() * self.dt).to(a.dtype)

    def forward(self, z: torch.Tensor, s: torch.Tensor) -> torch.Tensor:
        """z_{k+1} = K z_k for (B, r) latent states and (B, r) embeddings."""
        return (self.operator(s) @ z[..., None])[..., 0]
