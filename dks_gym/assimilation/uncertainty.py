"""The predictive uncertainty of a decoded filter estimate, and the scores of that uncertainty.

The filters carry a latent covariance; the fields a user sees are decoded. Per cell the predictive variance is

* EKF and forward run: ``diag(G P G^T)`` with ``G = d decode / dz`` at the filter mean (the first-order,
  "delta method" push of the latent covariance ``P`` through the decoder). It is computed as
  ``sum_j (G l_j)^2`` over the columns ``l_j`` of a factor ``L L^T = P``, never the ``(C n_cells, r)``
  Jacobian itself: by the model's own exact rule (``decoder_variance``: the neural models' decoder
  linearized by hand, :mod:`dks_gym.models.decoder_variance`; pDMD's constant ``G`` times ``L``), or for
  any other model by ``r`` Jacobian-vector products of the decoder (forward-mode autodiff, vmapped over
  the columns so the primal pass is shared).
* EnKF: the sample variance (divisor ``n - 1``) of the decoded members, every member decoded.

plus, when given, the decoder's own reconstruction-error variance per cell (:func:`reconstruction_variance`):
the filter's covariance says how unsure the latent state is, not how well the decoder can represent the
field at all. The scores of a Gaussian prediction ``N(mean, std^2)`` against the truth, averaged over the
cells of the scored channels (as the Eq. 18 MSE is): :func:`gaussian_scores` (coverage of the central 95 %
interval, NEES per cell, CRPS, :func:`gaussian_crps`, and the MSE the std predicts).
"""

from __future__ import annotations

import math
import warnings
from typing import Any, Sequence

import numpy as np
import torch

from ..dataset import Dataset
from ..filters.covariance import psd_sqrt
from ..models import FilterableModel, LatentModel
from ..models.calibration import calibrate
from .errors import scored_channels

#: The two-sided 95 % quantile of the standard normal, Phi^-1(0.975).
Z95 = 1.959963984540054
#: How many numbers one chunk of decoded fields may hold (per JVP call, per decode, per G L block): 2^22,
#: 16 MB in float32. The sphere (4 x 64^3 cells) decodes 4 rows per call; Burgers 4096.
CHUNK_NUMBERS = 2**22
#: Scores divide by the std floored at this fraction of each channel's data std (a cell with no variance
#: at all, e.g. inside a solid body of a linear model, must not divide by zero).
STD_FLOOR = 1e-6
_SQRT_PI = math.sqrt(math.pi)
_SQRT_2 = math.sqrt(2.0)
_SQRT_2PI = math.sqrt(2.0 * math.pi)
_EXP_FLOOR = -87.0  # exp(-87) = 1.6e-38: the smallest exponent whose float32 exp is a normal number


def _quiet_jvp(fn: Any, primal: torch.Tensor, tangent: torch.Tensor) -> torch.Tensor:
    with warnings.catch_warnings():
        # torch's forward-mode AD loads its decompositions through torch.jit.script, which torch itself deprecates.
        warnings.filterwarnings("ignore", message=r".*torch\.jit\.script.* is deprecated", category=DeprecationWarning)
        return torch.func.jvp(fn, (primal,), (tangent,))[1]


def _field_size(model: FilterableModel, z: torch.Tensor, mu: torch.Tensor) -> int:
    """Numbers in one decoded field: C * n_cells from the model's shape, or from one decode."""
    if hasattr(model, "n_fields") and hasattr(model, "grid"):
        return int(model.n_fields) * int(np.prod(model.grid))
    with torch.no_grad():
        return int(np.prod(model.decode(z[:1], mu[:1]).shape[1:]))


def jacobian_variance(model: FilterableModel, z: torch.Tensor, mu: torch.Tensor, P: torch.Tensor) -> torch.Tensor:
    """``diag(G P G^T)`` per batch element, ``(B, C, n_cells)``, with ``G = d decode(z, mu) / dz`` at ``z``.

    ``z`` (B, r), ``mu`` (B,), ``P`` (B, r, r) symmetric positive semi-definite. With ``L L^T = P``:
    ``diag(G P G^T) = sum_j (G L[:, j])^2``. A model's own exact rule where it has one
    (``model.decoder_variance(z, mu, L)``: the neural models linearize their decoder by hand, pDMD's is
    affine); otherwise one Jacobian-vector product of the decoder per column of ``L`` (forward mode,
    vmapped over the columns), in chunks of elements and columns holding at most :data:`CHUNK_NUMBERS`
    output numbers (plus the decoder's activations); ``G`` itself is never formed.
    """
    z, L = z.detach(), _covariance_factor(P, z)
    own = getattr(model, "decoder_variance", None)
    var = None if own is None else own(z, torch.as_tensor(mu, device=z.device), L)
    return _jvp_variance(model, z, mu, L) if var is None else var.flatten(2)


def decoded_variance(model: FilterableModel, z: torch.Tensor, mu: torch.Tensor,
                     P: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``model.decode(z, mu)`` (B, C, *grid) and :func:`jacobian_variance` (B, C, n_cells) together: from one
    forward pass of the decoder where the model shares it (``model.decode_with_variance``: the neural
    models' GELU inputs are what their exact rule linearizes at), else the two calls."""
    own = getattr(model, "decode_with_variance", None)
    if own is None:
        return model.decode(z, mu), jacobian_variance(model, z, mu, P)
    z, L = z.detach(), _covariance_factor(P, z)
    field, var = own(z, torch.as_tensor(mu, device=z.device), L)
    return field, _jvp_variance(model, z, mu, L) if var is None else var.flatten(2)


def _covariance_factor(P: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    """``L`` with ``L L^T = P`` (symmetrized first: round-off), in ``like``'s dtype and device."""
    return psd_sqrt(0.5 * (P + P.mT)).to(like)


def _jvp_variance(model: FilterableModel, z: torch.Tensor, mu: torch.Tensor, L: torch.Tensor) -> torch.Tensor:
    """:func:`jacobian_variance` by ``r`` Jacobian-vector products of ``decode``, for any model."""
    batch, r = z.shape
    mu = torch.as_tensor(mu, device=z.device)
    n_out = _field_size(model, z, mu)
    # Per call: (elements x directions) tangent fields of n_out numbers each, at most CHUNK_NUMBERS in all.
    per_element = max(1, CHUNK_NUMBERS // (n_out * r))
    directions = r if n_out * r <= CHUNK_NUMBERS else max(1, CHUNK_NUMBERS // n_out)
    parts = []
    for b in range(0, batch, per_element):
        zb, mb, Lb = z[b:b + per_element], mu[b:b + per_element], L[b:b + per_element]
        var = None
        for j in range(0, r, directions):
            cols = _tangent_fields(model, zb, mb, Lb[:, :, j:j + directions].permute(2, 0, 1))  # (d, b, C, ...)
            sq = cols.pow(2).sum(0)
            var = sq if var is None else var + sq
        parts.append(var.flatten(2))
    return torch.cat(parts)


def _tangent_fields(model: FilterableModel, z: torch.Tensor, mu: torch.Tensor,
                    tangents: torch.Tensor) -> torch.Tensor:
    """``d decode(z, mu)[t]`` for each of the tangents ``(d, B, r)``: ``(d, B, C, *grid)``.

    One forward-mode pass vmapped over the tangents (the primal pass is shared, about 2-3x faster than
    stacking the directions as rows); decoders whose operations lack vmap rules fall back to stacked rows.
    """

    def decode(x: torch.Tensor) -> torch.Tensor:
        return model.decode(x, mu)

    try:
        return torch.func.vmap(lambda t: _quiet_jvp(decode, z, t))(tangents).detach()
    except (RuntimeError, NotImplementedError):
        d, batch = tangents.shape[:2]
        rows_mu = mu.repeat(d)
        out = _quiet_jvp(lambda x: model.decode(x, rows_mu), z.repeat(d, 1), tangents.reshape(d * batch, -1))
        return out.detach().reshape(d, batch, *out.shape[1:])


def ensemble_variance(model: FilterableModel, ensemble: torch.Tensor, mu: torch.Tensor,
                      center: torch.Tensor | None = None) -> torch.Tensor:
    """Sample variance (divisor ``n - 1``) over the members of the decoded ensemble ``(B, n, r)``: ``(B, C, n_cells)``.

    Every member is decoded, in chunks of rows of at most :data:`CHUNK_NUMBERS` numbers; the sums are
    shifted by ``center`` (B, C, *grid) (e.g. the decoded mean; default the first member) for accuracy.
    """
    return decoded_ensemble(model, ensemble, mu, center)[0]


def decoded_ensemble(model: FilterableModel, ensemble: torch.Tensor, mu: torch.Tensor,
                     center: torch.Tensor | None = None,
                     cells: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor | None]:
    """:func:`ensemble_variance` and, from the same decodes, the members' values at ``cells`` (B, k), flat
    indices into each element's decoded field (``channel * n_cells + cell``): ``(var, values (B, n, k))``
    (values None without cells). The rank histograms read the members there."""
    batch, n, r = ensemble.shape
    rows = ensemble.detach().reshape(batch * n, r)
    rows_mu = torch.as_tensor(mu).repeat_interleave(n, dim=0)
    owner = torch.arange(batch, device=rows.device).repeat_interleave(n)
    with torch.no_grad():
        if center is None:
            center = model.decode(ensemble[:, 0], mu)
        shift = center.flatten(2)
        n_out = shift[0].numel()
        step = max(1, CHUNK_NUMBERS // n_out)
        s1 = torch.zeros_like(shift)
        s2 = torch.zeros_like(shift)
        at = None if cells is None else torch.as_tensor(cells, device=rows.device).repeat_interleave(n, dim=0)
        values = None if cells is None else torch.empty(batch * n, at.shape[1], dtype=shift.dtype, device=rows.device)
        for s in range(0, batch * n, step):
            decoded = model.decode(rows[s:s + step], rows_mu[s:s + step]).flatten(2)
            if values is not None:
                values[s:s + step] = decoded.flatten(1).gather(1, at[s:s + step])
            d = decoded - shift[owner[s:s + step]]
            s1.index_add_(0, owner[s:s + step], d)
            s2.index_add_(0, owner[s:s + step], d.pow(2))
    var = ((s2 - s1.pow(2) / n) / (n - 1)).clamp_min(0.0)
    return var, None if values is None else values.reshape(batch, n, -1)


def reconstruction_variance(model: LatentModel, dataset: Dataset | str, trajectories: Sequence[int] | np.ndarray,
                            split: str = "train") -> np.ndarray:
    """The decoder's reconstruction-error variance per cell, ``(C, *grid)`` float64, physical units squared.

    The mean over every frame of the given trajectories of ``(decode(encode(x)) - x)^2``: what the model
    cannot represent even with the latent state known exactly; :func:`dks_gym.models.calibrate` computes
    it (training stores it as ``model.calibration["reconstruction_variance"]``, on held-out trajectories).
    Use trajectories the model was not trained on, else it is optimistic.
    """
    ds = dataset if isinstance(dataset, Dataset) else Dataset(dataset)
    index = [int(t) for t in np.asarray(trajectories, dtype=np.int64).reshape(-1)]
    if not index:
        raise ValueError("reconstruction_variance needs at least one trajectory")
    return calibrate(model, ds, index, split)["reconstruction_variance"].double().numpy()


def gaussian_crps(x: Any, mean: Any, std: Any) -> Any:
    """CRPS of ``N(mean, std^2)`` at ``x``, elementwise: ``std [z (2 Phi(z) - 1) + 2 phi(z) - 1/sqrt(pi)]``,
    ``z = (x - mean) / std`` (Gneiting and Raftery 2007). Tensors in, a tensor out; otherwise numpy."""
    as_numpy = not any(isinstance(v, torch.Tensor) for v in (x, mean, std))
    x, mean, std = (torch.as_tensor(v, dtype=torch.float64) if as_numpy else v for v in (x, mean, std))
    crps = _crps(((x - mean) / std), std)
    return crps.numpy() if as_numpy else crps


def _crps(z: torch.Tensor, std: torch.Tensor) -> torch.Tensor:
    """:func:`gaussian_crps` from the standardized error ``z``. ``2 Phi(z) - 1 = erf(z / sqrt 2)``: the same to
    round-off, and torch's float64 erf is 10x faster than its ndtr."""
    return std * (z * torch.erf(z / _SQRT_2) + 2.0 * torch.exp(-0.5 * z * z) / _SQRT_2PI - 1.0 / _SQRT_PI)


def gaussian_scores(estimate: torch.Tensor, std: torch.Tensor, truth: torch.Tensor, scored: Sequence[int],
                    channel_std: torch.Tensor | np.ndarray | None = None) -> dict[str, np.ndarray]:
    """Scores of the per-cell predictions ``N(estimate, std^2)`` against ``truth``, all ``(B, C, *grid)``,
    over the ``scored`` channels and every cell (as :func:`~dks_gym.assimilation.field_errors`), per element:

    * ``coverage``: the fraction of cells whose truth lies in the central 95 % interval ``estimate +- 1.96 std``
      (0.95 when calibrated);
    * ``nees``: the mean over cells of ``(truth - estimate)^2 / std^2`` (1 when calibrated);
    * ``crps``: the mean over cells of :func:`gaussian_crps` (physical units; lower is better);
    * ``predicted_mse``: the mean over cells of ``std^2``, the MSE the std predicts (Eq. 18 when calibrated;
      the spread-skill ratio compares them, :mod:`~dks_gym.assimilation.spread`).

    ``std`` is floored at :data:`STD_FLOOR` times ``channel_std`` (C,) (default 1) so that a cell without
    variance does not divide by zero. The per-cell terms are computed in the estimate's dtype (float32 for
    the shipped models: 1e-7 relative, and 3-6x faster than float64), their means accumulated in float64.
    Returns (B,) float64 arrays.
    """
    idx = list(scored)
    pick = scored_channels(idx)
    mean = estimate[:, pick].flatten(2)
    x = truth[:, pick].flatten(2).to(mean)
    s = std[:, pick].flatten(2).to(mean)
    floor = torch.ones(len(idx), dtype=mean.dtype, device=mean.device) if channel_std is None \
        else torch.as_tensor(channel_std, device=mean.device).to(mean.dtype)[idx]
    s = torch.maximum(s, STD_FLOOR * floor[None, :, None])
    err = x - mean
    z = err / s
    cells = z[0].numel()

    def mean_of(t: torch.Tensor) -> np.ndarray:
        return (t.sum(dim=(1, 2), dtype=torch.float64) / cells).cpu().numpy()

    # In place where a term is this call's own: each pass over a vector env's fields costs as much as the
    # arithmetic, and fresh memory a page fault per 4 kB.
    coverage = mean_of(err.abs_() <= Z95 * s)
    z2 = z.square()
    nees = mean_of(z2)
    # _crps, with z^2 shared with the NEES. The exponent is floored where exp(-z^2 / 2) leaves the normal
    # floats (|z| > 13.2: an overconfident filter's cells), where x86 exp runs 10x slower; there the term is
    # below 1e-38 against z erf(z / sqrt 2) > 13, so the CRPS is the same to round-off.
    phi = z2.mul_(-0.5).clamp_min_(_EXP_FLOOR).exp_()
    crps = torch.div(z, _SQRT_2).erf_().mul_(z).add_(phi, alpha=2.0 / _SQRT_2PI)
    crps = mean_of(crps.sub_(1.0 / _SQRT_PI).mul_(s))
    return {"coverage": coverage, "nees": nees, "crps": crps, "predicted_mse": mean_of(s.square_())}


__all__ = [
    "CHUNK_NUMBERS",
    "STD_FLOOR",
    "Z95",
    "decoded_ensemble",
    "decoded_variance",
    "ensemble_variance",
    "gaussian_crps",
    "gaussian_scores",
    "jacobian_variance",
    "reconstruction_variance",
]
