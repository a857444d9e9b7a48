"""The Koopman latent map: K(mu; dt) = exp(A(mu) dt) with A = Q - Q^T - diag(d * d) (Eqs. 7-9)."""

from __future__ import annotations

import math

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


def taylor_matrix_exp(a: torch.Tensor) -> torch.Tensor:
    """exp(a) for a batch of square matrices (B, n, n) by scaling and squaring a truncated Taylor series, in
    ``a``'s dtype, differentiable by autograd through its batched matrix products.

    ``a`` is scaled by 2^-s so that every matrix has 1-norm theta <= 1; the series stops at the first degree m
    whose remainder bound theta^(m+1) / (m+1)! is below the dtype's unit round-off (2^-24 in float32); the
    result is squared s times. In float32 it is as close to ``torch.linalg.matrix_exp`` in float64 as float32's
    own ``matrix_exp`` is (tests/test_models.py), and its forward and backward together cost a tenth of the
    float64 ``matrix_exp``'s on a CPU core at r = 32 (torch differentiates ``matrix_exp`` through the
    exponential of a 2r x 2r block matrix).
    """
    tol = torch.finfo(a.dtype).eps / 2
    with torch.no_grad():
        norm = float(a.abs().sum(-2).amax()) if a.numel() else 0.0  # the largest 1-norm of the batch
    squarings = max(0, math.ceil(math.log2(norm))) if norm > 1 else 0
    theta = norm / 2**squarings
    degree, bound = 1, theta * theta / 2
    while bound > tol:
        degree += 1
        bound *= theta / (degree + 1)
    a = a / 2**squarings
    eye = torch.eye(a.shape[-1], dtype=a.dtype, device=a.device).expand_as(a)
    p = eye + a / degree  # Horner: I + a (I + a/2 (... (I + a/m)))
    for k in range(degree - 1, 0, -1):
        p = torch.baddbmm(eye, a, p, alpha=1.0 / k)
    for _ in range(squarings):
        p = p @ p
    return p


class KoopmanOperator(nn.Module):
    """Parameter-dependent linear latent map z_{k+1} = K(mu; dt) z_k (Eq. 7).

    Q_theta: R^r -> R^{r^2} and d_theta: R^r -> R^r act on the embedding s = e(mu) (Table
    koopman_mlp_hparams); at r = 32 they have 38,016 + 5,280 = 43,296 parameters. A has a skew-symmetric
    part and a diagonal <= 0, so ||K||_2 <= 1 (non-expansive) for any weights. Out of training mode (the
    filters, validation, evaluation) the matrix exponential is evaluated in float64 and cast back, so that
    rounding does not push ||K||_2 above 1 by more than ~1e-7. In training mode it is
    :func:`taylor_matrix_exp` in the model's float32: the same K to float32 round-off, and its backward is
    cheap (``torch.linalg.matrix_exp``'s float64 backward was a fifth of a lite Burgers training step).
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
        if self.training:
            return taylor_matrix_exp(a * self.dt)
        return torch.linalg.matrix_exp(a.double() * self.dt).to(a.dtype)

    def forward(self, z: torch.Tensor, s: torch.Tensor) -> torch.Tensor:
        """z_{k+1} = K z_k for (B, r) latent states and (B, r) embeddings."""
        return (self.operator(s) @ z[..., None])[..., 0]
