"""The training loss of the latent models (Eq. 10, multi-step form Eq. 11), on a batch of windows.

Lambda_1 = lambda_2 = lambda_3 = 1. For a window x_k, ..., x_{k+T} of one training trajectory with
parameter mu::

    z_j   = E(x_{k+j}, mu)                      encodings of every frame of the window (targets)
    zh_0  = z_0,  zh_{j+1} = F(zh_j, mu)        unrolled from the first encoding only
    L     = mse(G(z_0), x_k)                                        reconstruction, initial step only
          + 1/T sum_{j=1..T} mse(G(zh_j), x_{k+j})                  decoded prediction
          + 1/T sum_{j=1..T} mse(zh_j, z_j)                         latent prediction

``mse`` is the mean of the squared differences over every element (batch, channels, grid cells; for
the latent term batch and the r latent coordinates), in normalized units: G is
``decode_normalized`` and the targets are ``reconstruction_target`` (per-channel standardized fields,
plus the cell type on the sphere, whose decoder outputs it). Per-element means put the three terms on
the same scale whatever the grid size and r; the paper's squared norms would weight the field terms by
N / r relative to the latent term. Gradients flow through the target encodings z_j (j >= 1) as well:
the paper does not say, this is the common choice, and the reconstruction term keeps the encoder from
collapsing to make the latent term trivial.
"""

from __future__ import annotations

import torch

from .latent_model import NeuralLatentModel

LOSS_TERMS = ("total", "reconstruction", "prediction", "latent")


def training_loss(
    model: NeuralLatentModel, window: torch.Tensor, mu: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Eq. 10 (T = 1) / Eq. 11 on a batch of windows (B, T + 1, C, *grid) in physical units, mu (B,).

    Returns the scalar loss and the detached (4,) vector (total, reconstruction, prediction, latent).
    All frames are encoded, and the reconstruction and the T predictions decoded, in one batched call each.
    """
    if window.ndim < 3 or window.shape[1] < 2:
        raise ValueError(
            f"a training window must have shape (B, T + 1, C, *grid) with T >= 1, got {tuple(window.shape)}"
        )
    b, n = window.shape[:2]
    horizon = n - 1
    frames = window.reshape(b * n, *window.shape[2:])
    mu_frames = mu.repeat_interleave(n)
    z_true = model.encode(frames, mu_frames).view(b, n, model.r)
    target = model.reconstruction_target(frames).view(b, n, -1)
    z_hat = [z_true[:, 0]]
    for _ in range(horizon):  # Eq. 11: unrolled from one encoding, no re-injection
        z_hat.append(model.forecast(z_hat[-1], mu))
    z_pred = torch.stack(z_hat[1:], dim=1)  # (B, T, r)
    # Decode z_0 and zh_1..zh_T together: rows ordered (b, j) with j = 0..T.
    decoded = model.decode_normalized(torch.stack(z_hat, dim=1).reshape(b * n, model.r), mu_frames).view(b, n, -1)
    reconstruction = torch.mean((decoded[:, 0] - target[:, 0]) ** 2)
    prediction = torch.mean((decoded[:, 1:] - target[:, 1:]) ** 2)
    latent = torch.mean((z_pred - z_true[:, 1:]) ** 2)
    loss = reconstruction + prediction + latent
    return loss, torch.stack([loss, reconstruction, prediction, latent]).detach()



__all__ = ["LOSS_TERMS", "training_loss"]
