"""Scoring sensor layouts with the filter in the loop: many layouts on many trajectories in one batched filter.

* :func:`run_layouts`: the real filter (forward run, EKF or EnKF: :func:`dks_gym.assimilation.run_episodes`)
  for B (layout, trajectory) pairs at once. Readings come from :class:`~dks_gym.envs.SensingEnv` objects,
  one per trajectory, that read the union of all layouts' cells, so each pair sees exactly the noise the
  harness and the environments give that cell (the noise depends on (noise seed, split, trajectory, frame,
  cell) only). Used by the greedy baseline, the sequential MDP's reward and the evaluation harness.
* :func:`run_adaptive`: the same loop with a layout chosen every step by an adaptive policy
  (``sensor_mode="select"`` environments).
* :func:`covariance_traces`: the trace of the EKF analysis covariance (Eqs. 14, 15, 17) along the encoded
  true trajectories, for many layouts at once. Linearizing at the truth rather than at the filter's own
  estimate makes it independent of the noise realization and needs no decoding per layout: one decoder
  Jacobian per frame serves every layout.
"""

from __future__ import annotations

from typing import Any, Callable

import numpy as np
import torch

from dks_gym.assimilation import AssimilationConfig, AssimilationResult, run_dataset
from dks_gym.dataset import Dataset
from dks_gym.envs.noise import noise_sigma
from dks_gym.filters import GaussianState, LatentDynamics, as_covariance, ekf_forecast, ekf_update
from dks_gym.models import FilterableModel, model_device


def _episode_seeds(config: AssimilationConfig, n: int, noise_seeds: Any) -> np.ndarray:
    seeds = np.full(n, config.noise_seed, dtype=np.int64) if noise_seeds is None else \
        np.asarray(noise_seeds, dtype=np.int64).reshape(-1)
    if seeds.shape != (n,):
        raise ValueError(f"noise_seeds must hold one seed per episode ({n}), got {seeds.shape[0]}")
    return seeds


def run_layouts(model: FilterableModel, dataset: Dataset, layouts: np.ndarray, trajectories: np.ndarray,
                config: AssimilationConfig, *, split: str | None = None, noise_seeds: np.ndarray | None = None,
                dtype: torch.dtype = torch.float32) -> AssimilationResult:
    """Filter B (layout, trajectory) pairs of ``split`` (default ``config.split``) as one batch.

    ``layouts`` (B, m) flat grid indices, ``trajectories`` (B,) indices into the split, ``noise_seeds``
    (B,) the noise seed of each episode (default ``config.noise_seed`` for all). Returns an
    :class:`~dks_gym.assimilation.AssimilationResult` whose ``step_mse`` is (B, n_t) (frame 0 is the initial
    estimate, the same for every layout) and ``extras["layouts"]`` the layouts.
    """
    split = split or config.split
    layouts = np.atleast_2d(np.asarray(layouts, dtype=np.int64))
    trajectories = np.asarray(trajectories, dtype=np.int64).reshape(-1)
    n_split = dataset.n_trajectories(split)
    if layouts.ndim != 2 or layouts.shape[0] != trajectories.shape[0] or layouts.shape[0] == 0:
        raise ValueError(f"layouts must be (B, m) with one row per trajectory, got {layouts.shape} for "
                         f"{trajectories.shape[0]} trajectories")
    if trajectories.min() < 0 or trajectories.max() >= n_split:
        raise ValueError(f"trajectories must be indices in [0, {n_split}) of the {split!r} split")
    seeds = _episode_seeds(config, len(trajectories), noise_seeds)
    # One env per (trajectory, seed) reads the union of all layouts' cells: each pair sees exactly the noise
    # the environments give that cell, which depends on (noise seed, split, trajectory, frame, cell) only.
    result = run_dataset(model, dataset, trajectories, seeds, config, split=split, share=True, layouts=layouts,
                         dtype=dtype, sensors=np.unique(layouts), uncertainty=False)  # rankings score the MSE
    result.extras["noise_seeds"] = seeds
    return result


def forward_reference(model: FilterableModel, dataset: Dataset, config: AssimilationConfig,
                      split: str = "train") -> np.ndarray:
    """Per trajectory of ``split``, the forward run's (no assimilation) MSE averaged over frames 1..n_t-1, (n,).

    The sensors do not matter for a forward run, so this is the scale the learned policies' rewards are
    divided by: a layout scores 1 when the filter does no better than the open-loop model.
    """
    n = dataset.n_trajectories(split)
    layout = dataset.benchmark.paper_layout(config.n_sensors) if config.n_sensors <= 32 else \
        np.flatnonzero(dataset.benchmark.fluid_mask(dataset.cell_type).ravel())[: config.n_sensors]
    result = run_layouts(model, dataset, np.repeat(np.asarray(layout)[None], n, 0), np.arange(n),
                         config.replace(kind="forward"), split=split)
    return result.step_mse[:, 1:].mean(axis=1)


def run_adaptive(model: FilterableModel, dataset: Dataset, decide: Callable[[np.ndarray], np.ndarray],
                 candidates: np.ndarray, trajectories: np.ndarray, config: AssimilationConfig, *,
                 noise_seeds: np.ndarray | None = None,
                 dtype: torch.dtype = torch.float32) -> AssimilationResult:
    """Filter the trajectories of ``config.split`` with a layout per step: ``decide(belief (B, 2r)) -> (B, m)``.

    ``decide`` returns indices into ``candidates`` (each row distinct); ``noise_seeds`` as in
    :func:`run_layouts`. ``extras`` holds ``layouts`` (B, n_t - 1, m) flat grid indices read at frames
    1..n_t-1 and ``decision_seconds`` (n_t - 1,), the wall time of each batched decision.
    """
    trajectories = np.asarray(trajectories, dtype=np.int64).reshape(-1)
    seeds = _episode_seeds(config, len(trajectories), noise_seeds)
    result = run_dataset(model, dataset, trajectories, seeds, config, decide=decide, dtype=dtype,
                         n_sensors=config.n_sensors, sensor_mode="select",
                         candidates=np.asarray(candidates, dtype=np.int64), uncertainty=False)
    result.extras["noise_seeds"] = seeds
    return result


def decoder_jacobians(model: FilterableModel, z: torch.Tensor, mu: torch.Tensor, cells: np.ndarray, channel: str,
                      scored: tuple[int, ...], chunk: int | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Jacobians of the decoder at each latent state, detached, as (J, M):

    J (n, len(cells), r) = dh/dz of the decoded ``channel`` at ``cells``; M (n, r, r) = G^T G / n_out with
    G = d decode / dz over the ``scored`` channels and every cell, so that trace(M P) is the mean variance
    of the decoded field under a latent covariance P. G comes from the model's ``decoder_jacobian``, in
    chunks of ``chunk`` states (default: as many as keep it under about 2e7 numbers).
    """
    c = model.shape.channels.index(channel)
    idx = torch.as_tensor(cells, dtype=torch.long, device=z.device)
    r = z.shape[1]
    n_out = model.n_fields * int(np.prod(model.grid))
    chunk = chunk or int(np.clip(2e7 // (n_out * r), 1, 64))
    Js, Ms = [], []
    for s in range(0, z.shape[0], chunk):
        G = model.decoder_jacobian(z[s:s + chunk], mu[s:s + chunk])  # (chunk, C, n_cells, r)
        Js.append(G[:, c, idx])
        Gs = G[:, list(scored)].flatten(1, 2)
        Ms.append(Gs.mT @ Gs / Gs.shape[1])
    return torch.cat(Js), torch.cat(Ms)


class LinearizedTrajectories:
    """Encoded training trajectories with their forecast and observation Jacobians, for :func:`covariance_traces`.

    Per trajectory: sigma (the env's noise level times max |observed channel|), F_k = df/dz at the encoded
    true state z_k (Koopman: K(mu), pDMD: A~(mu)), J_k = dh/dz at z_k for every cell in ``cells`` and the
    field weight M_k = G_k^T G_k / n_out of the decoder Jacobian over the scored channels. Building it
    costs one encoder pass and r decoder Jacobian-vector products per frame (the greedy trace baseline's
    main cost).
    """

    def __init__(self, model: FilterableModel, dataset: Dataset, trajectories: np.ndarray, cells: np.ndarray,
                 config: AssimilationConfig, *, split: str = "train", dtype: torch.dtype = torch.float64) -> None:
        bench = dataset.benchmark
        device = model_device(model)
        self.model = model  # resolves the config's named P0 and Q ("calibrated")
        self.cells = np.unique(np.asarray(cells, dtype=np.int64))
        self.trajectories = np.asarray(trajectories, dtype=np.int64)
        fluid = bench.fluid_mask(dataset.cell_type)
        F, J, M, sigma = [], [], [], []
        for t in self.trajectories:
            x = dataset.trajectory(split, int(t))
            mu = torch.full((x.shape[0],), float(dataset.params(split)[t]), device=device)
            sigma.append(max(noise_sigma(x[:, bench.observed_index], fluid, config.noise_level), 1e-12))
            xt = torch.from_numpy(x).to(device)
            with torch.no_grad():
                z = torch.cat([model.encode(xt[s:s + 16], mu[s:s + 16]) for s in range(0, len(xt), 16)])
            Fk = model.forecast_jacobian(z[:-1], mu[:-1]).detach()
            F.append(Fk.expand(len(z) - 1, *Fk.shape[-2:]) if Fk.ndim == 2 else Fk)
            Jt, Mt = decoder_jacobians(model, z, mu, self.cells, bench.observed_channel, bench.scored_indices)
            J.append(Jt)
            M.append(Mt)
        self.F = torch.stack(F).to(dtype)  # (T, n_t - 1, r, r)
        self.J = torch.stack(J).to(dtype)  # (T, n_t, n_cells, r)
        self.M = torch.stack(M).to(dtype)  # (T, n_t, r, r)
        self.sigma = torch.tensor(sigma, dtype=dtype, device=device)  # (T,)


_LAST_LINEARIZED: list[tuple[tuple, LinearizedTrajectories]] = []  # one slot: a budget sweep reuses its lattice


def linearized(model: FilterableModel, dataset: Dataset, trajectories: np.ndarray, cells: np.ndarray,
               config: AssimilationConfig) -> LinearizedTrajectories:
    """:class:`LinearizedTrajectories` of these arguments, the last one built reused when they match (the
    greedy policies of a budget sweep or of several fault scenarios share one candidate lattice; only the
    config's noise level enters)."""
    key = (model, str(dataset.path), np.asarray(trajectories).tobytes(), np.unique(cells).tobytes(),
           float(config.noise_level))
    if _LAST_LINEARIZED and _LAST_LINEARIZED[0][0][0] is model and _LAST_LINEARIZED[0][0][1:] == key[1:]:
        return _LAST_LINEARIZED[0][1]
    lin = LinearizedTrajectories(model, dataset, trajectories, cells, config)
    _LAST_LINEARIZED[:] = [(key, lin)]
    return lin


def covariance_traces(lin: LinearizedTrajectories, layouts: np.ndarray, config: AssimilationConfig,
                      space: str = "field") -> np.ndarray:
    """Trace of the EKF analysis covariance linearized along the encoded truth, (L, T, n_t - 1).

    For L layouts and T trajectories at frames 1..n_t-1. ``space="field"``: trace(M_k P_a) = the mean
    variance of the decoded scored field, the MSE the filter expects (physical units; latent directions the
    decoder ignores do not count); ``space="latent"``: trace(P_a).

    The recursion is the filters' own :func:`~dks_gym.filters.ekf_forecast` / :func:`~dks_gym.filters.ekf_update`
    (Eqs. 14, 15, 17 with P0, Q of ``config`` and R = sigma^2 I), started at P0 I at frame 0 and updated
    at frames 1..n_t-1. Adding a sensor can only shrink P_a (in the Loewner order, at every step), so a
    greedy search on this objective improves monotonically.
    """
    if space not in ("field", "latent"):
        raise ValueError(f"space must be 'field' or 'latent', got {space!r}")
    layouts = np.atleast_2d(np.asarray(layouts, dtype=np.int64))
    missing = ~np.isin(layouts, lin.cells)
    if missing.any():
        raise ValueError(f"layout cells {np.unique(layouts[missing])[:10].tolist()} have no Jacobian; "
                         "build LinearizedTrajectories with every candidate cell")
    n_layouts, n_traj = len(layouts), len(lin.trajectories)
    position = torch.as_tensor(np.searchsorted(lin.cells, layouts), device=lin.J.device)  # (L, m)
    which = torch.arange(n_traj, device=lin.J.device).repeat(n_layouts)  # element b = (layout b // T, traj b % T)
    rows = position.repeat_interleave(n_traj, dim=0)  # (L T, m)
    r = lin.F.shape[-1]
    batch = n_layouts * n_traj
    zeros = torch.zeros(batch, r, dtype=lin.J.dtype, device=lin.J.device)
    Q = as_covariance(config.filter.process_noise(lin.model), batch, r, like=zeros, name="Q")
    P0 = as_covariance(config.filter.initial_covariance(lin.model), batch, r, like=zeros, name="P0")
    state = GaussianState(zeros, P0.clone())
    R = lin.sigma[which] ** 2
    y = torch.zeros(batch, layouts.shape[1], dtype=lin.J.dtype, device=lin.J.device)
    traces = []
    for k in range(1, lin.J.shape[1]):
        Jk = lin.J[which[:, None], k, rows]  # (L T, m, r)
        dynamics = LatentDynamics(lambda z: z, lambda z: torch.zeros_like(y), forecast_jacobian=lin.F[which, k - 1],
                                  observe_jacobian=Jk)
        state, _ = ekf_forecast(state, dynamics, Q)
        state, _ = ekf_update(state, y, dynamics, R)
        if space == "field":
            traces.append((lin.M[which, k] * state.cov).sum(dim=(-2, -1)))  # trace(M P), both symmetric
        else:
            traces.append(state.cov.diagonal(dim1=-2, dim2=-1).sum(-1))
    return torch.stack(traces, dim=1).reshape(n_layouts, n_traj, -1).cpu().numpy()


def episode_information(lin: LinearizedTrajectories) -> torch.Tensor:
    """What each candidate cell's readings over a whole episode tell about the initial latent state, (T, n_c, r, r).

    Under the linearized deterministic latent map (z_k = Phi_k z_0, Phi_k = F_{k-1} ... F_0; the Koopman
    model's is exactly linear, Phi_k = K(mu)^k), a reading at cell c and frame k is y = J_k[c] Phi_k z_0 + noise
    of variance sigma^2, so its Fisher information is ``(J_k[c] Phi_k)^T (J_k[c] Phi_k) / sigma^2``; summed
    over frames 1..n_t-1. A layout's information is the prior's plus the sum over its cells.
    """
    n_traj, n_t, n_cells, r = lin.J.shape
    phi = torch.eye(r, dtype=lin.J.dtype, device=lin.J.device).expand(n_traj, r, r)
    info = torch.zeros(n_traj, n_cells, r, r, dtype=lin.J.dtype, device=lin.J.device)
    for k in range(1, n_t):
        phi = lin.F[:, k - 1] @ phi
        rows = lin.J[:, k] @ phi  # (T, n_c, r): each cell's reading as a function of z_0
        info += rows[..., :, None] * rows[..., None, :]
    return info / (lin.sigma ** 2)[:, None, None, None]


def information_logdets(lin: LinearizedTrajectories, information: torch.Tensor, layouts: np.ndarray,
                        prior: torch.Tensor) -> np.ndarray:
    """log det(prior + sum of the layout's cells' information), (L, T): the D-optimality of each layout on each
    trajectory. ``information`` from :func:`episode_information`; ``prior`` (r, r), P0^{-1}."""
    layouts = np.atleast_2d(np.asarray(layouts, dtype=np.int64))
    missing = ~np.isin(layouts, lin.cells)
    if missing.any():
        raise ValueError(f"layout cells {np.unique(layouts[missing])[:10].tolist()} have no Jacobian; "
                         "build LinearizedTrajectories with every candidate cell")
    position = torch.as_tensor(np.searchsorted(lin.cells, layouts), device=information.device)  # (L, m)
    total = information[:, position].sum(dim=2)  # (T, L, r, r)
    return torch.linalg.slogdet(prior.to(total) + total)[1].T.cpu().numpy()
