"""The POD of the pDMD baseline, streamed one trajectory at a time (randomized SVD), with a fixed sign per
basis vector so that the basis does not depend on LAPACK's choices (thread count, CPU)."""

from __future__ import annotations

from typing import Any, Callable

import numpy as np
import torch


#: Seed of :func:`sign_reference`.
SIGN_SEED = 20240613


def sign_reference(n: int) -> torch.Tensor:
    """The fixed vector g (n,) float64 that orients the POD basis: each basis vector u has g^T u > 0.

    Standard normal draws of numpy's legacy ``RandomState`` (whose stream numpy keeps fixed across versions
    and platforms). g^T u is then N(0, 1) for any unit vector u, so it is never near zero by structure, as
    the largest entry of a mode can be (the two mirror-image extremes of an antisymmetric mode are equal
    up to round-off); a sign flip would need |g^T u| at round-off level.
    """
    return torch.from_numpy(np.random.RandomState(SIGN_SEED).standard_normal(n))


def streamed_pod(
    n_blocks: int,
    load_block: Callable[[int], torch.Tensor],
    r: int,
    *,
    oversample: int = 10,
    power_iterations: int = 2,
    seed: int = 0,
) -> dict[str, Any]:
    """Rank-r POD of snapshots delivered block by block, by randomized SVD with streamed products.

    ``load_block(b)`` returns block ``b`` of snapshots as rows, a (M_b, N) tensor (its dtype and device
    are used throughout). With X = [S_0; S_1; ...]^T (N x M) it follows Halko, Martinsson and Tropp
    (2011), Alg. 4.4: Y = X Omega, then ``power_iterations`` times Y = X X^T orth(Y), then
    B = orth(Y)^T X and an SVD of the small B. Each stage is one pass over the blocks.

    Returns ``basis`` (N, r) with orthonormal columns, ``singular_values`` (r,), ``coefficients`` a list
    of (M_b, r) blocks U_r^T X, ``energy`` the fraction of sum ||x||^2 captured, ``passes``. The sign of
    each basis vector is fixed by :func:`sign_reference` (g^T u_j > 0), so that the result does not depend
    on the sign LAPACK happens to pick.
    """
    if n_blocks < 1:
        raise ValueError("streamed_pod needs at least one block of snapshots")
    gen = torch.Generator().manual_seed(seed)
    y = None
    sizes: list[int] = []
    total_energy = 0.0
    for b in range(n_blocks):
        s = load_block(b)
        sizes.append(s.shape[0])
        if y is None:
            y = torch.zeros(s.shape[1], r + oversample, dtype=s.dtype, device=s.device)
        omega = torch.randn(s.shape[0], y.shape[1], generator=gen, dtype=s.dtype).to(s.device)
        y += s.T @ omega
        total_energy += float((s * s).sum())
    n_snapshots = sum(sizes)
    k = min(r + oversample, n_snapshots, y.shape[0])
    if r > k:
        raise ValueError(f"POD rank r = {r} exceeds the number of snapshots ({n_snapshots}) or grid values")
    y = y[:, :k]
    passes = 1
    for _ in range(power_iterations):
        q = torch.linalg.qr(y).Q
        y = torch.zeros_like(q)
        for b in range(n_blocks):
            s = load_block(b)
            y += s.T @ (s @ q)
        passes += 1
    q = torch.linalg.qr(y).Q
    small = torch.cat([(load_block(b) @ q).T for b in range(n_blocks)], dim=1)  # B = Q^T X, (k, M)
    passes += 1
    ub, sv, vt = torch.linalg.svd(small, full_matrices=False)
    basis = q @ ub[:, :r]
    # LAPACK may return either sign for each singular pair, and which one depends on the thread count and the
    # CPU. Fix it: every basis vector has a positive projection on a fixed pseudo-random vector.
    sign = torch.sign(sign_reference(basis.shape[0]).to(basis) @ basis)
    sign[sign == 0] = 1
    basis = basis * sign
    coeffs = (sv[:r, None] * (vt[:r] * sign[:, None])).T  # U_r^T X = Sigma_r V_r^T, as rows (M, r)
    return {
        "basis": basis,
        "singular_values": sv[:r],
        "coefficients": list(torch.split(coeffs, sizes)),
        "energy": float((sv[:r] ** 2).sum()) / total_energy if total_energy > 0 else 1.0,
        "passes": passes,
    }


__all__ = ["SIGN_SEED", "sign_reference", "streamed_pod"]
