"""The batched assimilation core: one latent model, one filter, B sensing episodes, one step at a time.

:class:`Assimilation` is the only place where a filter meets a model: it builds the filter for the
current episodes of B ``SensingEnv`` objects (their mu, noise sigma, sensors and initial condition),
and each :meth:`Assimilation.step` forecasts, updates with the readings, decodes and scores (Eqs. 13-18);
with ``uncertainty=True`` it also decodes the filter's covariance into a per-cell predictive standard
deviation and scores it (:mod:`dks_gym.assimilation.uncertainty`; the EnKF also ranks the truth among its
decoded members, :mod:`dks_gym.assimilation.spread`).
The wrappers call it once per env step; :func:`~dks_gym.assimilation.run_episodes` calls it over whole
episodes. Its filter state is private: callers see snapshots and the belief.
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch

from ..dataset import Dataset
from ..envs.sensing import SensingEnv
from ..filters import EKF, EnKF, LatentDynamics, bind_param
from ..filters.parameter import ParameterCoordinate, augment_with_parameter
from ..models import FilterableModel, LatentModel, model_device, model_dtype
from ..threads import torch_threads
from .config import FilterConfig
from .errors import ctf_score, field_errors, relative_l2_errors
from .spread import rank_cells, spread_skill, truth_ranks
from .uncertainty import decoded_ensemble, decoded_variance, gaussian_scores, jacobian_variance

# Per model, per dataset file: the approximate initial latent state (it costs one pass over the train split).
_APPROXIMATE_CACHE: "weakref.WeakKeyDictionary[FilterableModel, dict[str, torch.Tensor]]" = weakref.WeakKeyDictionary()


def approximate_initial_latent(model: FilterableModel, dataset: Dataset) -> torch.Tensor:
    """z0 = mean over the training trajectories of their encoded first frames (SPEC section 4), (r,).

    For pDMD the encoding is the POD projection, so this is the mean of their POD coefficients.
    """
    per_model = _APPROXIMATE_CACHE.setdefault(model, {})
    key = str(Path(dataset.path).resolve())
    if key not in per_model:
        first = np.asarray(dataset.fields("train")[:, 0], dtype=np.float32)
        mu = dataset.params("train")
        with torch.no_grad():
            z = torch.cat([model.encode(torch.from_numpy(first[i : i + 16]), torch.from_numpy(mu[i : i + 16]))
                           for i in range(0, len(first), 16)])
        per_model[key] = z.mean(0)
    return per_model[key]


@dataclass
class Snapshot:
    """The decoded estimate after a start or a step, with its errors (:mod:`~dks_gym.assimilation.errors`),
    per batch element."""

    estimate: torch.Tensor  # (B, C, *grid) decoded filter mean, physical units
    mse: np.ndarray  # (B,) Eq. 18, physical units
    normalized_mse: np.ndarray  # (B,) over standardized channels
    relative_l2: np.ndarray  # (B,) ||x^ - x|| / ||x|| over the scored channels (NaN where ||x|| = 0)
    channel_relative_l2: np.ndarray  # (B, n_scored) the same per scored channel, in the benchmark's order
    latent_mean: np.ndarray  # (B, r)
    diagnostics: dict[str, np.ndarray] = field(default_factory=dict)  # gain_norm, spread, (EKF) forecast_norm
    # With uncertainty (else None): the predictive std of every cell (B, C, *grid), physical units, and its
    # scores over the scored channels (B,): 95 % coverage, mean NEES per cell, mean Gaussian CRPS, the MSE
    # the std predicts (mean std^2).
    estimate_std: torch.Tensor | None = None
    coverage: np.ndarray | None = None
    nees: np.ndarray | None = None
    crps: np.ndarray | None = None
    # With an estimated parameter (else None), per element: mu's estimate, its std (delta method in the
    # estimated coordinate), the central 95 % interval, whether the estimate leaves the training range (the
    # model extrapolates there: flagged, not hidden), its relative error |mu^ - mu| / mu, whether the true
    # mu lies in the interval, and the estimated coordinate's std over its prior's (near 1: not identified).
    parameter: dict[str, np.ndarray] | None = None
    predicted_mse: np.ndarray | None = None
    # EnKF with uncertainty, after a step (else None): the rank of the truth among the n decoded members
    # (0..n, :func:`~dks_gym.assimilation.spread.truth_ranks`) at the sensors read (B, m) and at the fixed
    # cells of :func:`~dks_gym.assimilation.spread.rank_cells` (B, k).
    sensor_ranks: np.ndarray | None = None
    cell_ranks: np.ndarray | None = None

    @property
    def spread_skill(self) -> np.ndarray | None:
        """(B,) spread over skill of each element, ``sqrt(predicted_mse / mse)`` (None without uncertainty);
        biased high for one frame of one trajectory: average the squares first (:mod:`~dks_gym.assimilation.spread`)."""
        return None if self.predicted_mse is None else spread_skill(self.predicted_mse[None], self.mse[None])

    @property
    def score(self) -> np.ndarray:
        """(B,) the Common Task Framework's score 100 (1 - relative_l2) (:func:`~dks_gym.assimilation.ctf_score`)."""
        return ctf_score(self.relative_l2)


class _SensorRows:
    """The layouts h(z) reads, (B, m), updated every step so that chosen layouts are followed."""

    def __init__(self) -> None:
        self.current = np.zeros((1, 1), dtype=np.int64)

    def __call__(self, n_rows: int) -> np.ndarray:
        """Sensor indices of ``n_rows`` stacked rows (row j belongs to element j // (n_rows // B))."""
        return self.current.repeat(n_rows // len(self.current), axis=0)


class Assimilation:
    """One latent model and one batched filter following B sensing episodes (the B = 1 case is a wrapper).

    ``uncertainty`` (default True): every snapshot also holds ``estimate_std``, the predictive standard
    deviation of every cell, and its scores (coverage, NEES, CRPS); it costs r decoder Jacobian-vector
    products per element and step (EKF, forward run) or one decode per member (EnKF); False skips it.
    ``reconstruction_var``: the decoder's reconstruction-error variance per cell, (C, *grid) in physical
    units squared (:func:`~dks_gym.assimilation.reconstruction_variance`) or one number for every cell,
    added to the filter's variance; default: the model's own, measured on held-out trajectories when it
    was trained (``model.calibration["reconstruction_variance"]``), else zero; ``0`` switches it off.
    ``device``, ``dtype``: where and in what precision the filter runs (default: the model's).
    """

    def __init__(self, model: FilterableModel, config: FilterConfig, *, device: str | torch.device | None = None,
                 dtype: torch.dtype | None = None, uncertainty: bool = True,
                 reconstruction_var: Any = None) -> None:
        self.model = model
        self.config = config
        self.device = model_device(model) if device is None else torch.device(device)
        self.dtype = model_dtype(model) if dtype is None else dtype
        self.uncertainty = bool(uncertainty)
        if reconstruction_var is None:
            reconstruction_var = (getattr(model, "calibration", None) or {}).get("reconstruction_variance")
        self.reconstruction_var = None if reconstruction_var is None else _check_reconstruction_var(
            model, reconstruction_var, self.device, self.dtype)
        self._sensors = _SensorRows()
        self._filter: EKF | EnKF | None = None
        self._now: EKF | EnKF | None = None  # the filter as of the current frame (its lead when readings are late)
        self._lag = self._k = 0
        self._mu: torch.Tensor | None = None
        self._true_mu: np.ndarray | None = None
        self._coordinate: ParameterCoordinate | None = None  # set while mu is estimated
        self._prior_std = 1.0  # the estimated coordinate's prior std
        self._ranked: tuple[int, np.ndarray, np.random.Generator] | None = None  # EnKF: offset, cells, tie-breaks

    @property
    def filter(self) -> EKF | EnKF | None:
        """The running filter (read it for ``.mean``, ``.cov``, ``.diagnostics``; the core alone steps it)."""
        return self._filter

    def _dynamics(self, channel: str) -> LatentDynamics:
        """The model as the filters see it: mu bound (or estimated with the state, ``[z; s]``), h(z) =
        S(decode(z)) at each element's current sensors."""
        model, mu, rows = self.model, self._mu, self._sensors
        c = model.shape.channels.index(channel)

        def observe(z: torch.Tensor, m: torch.Tensor) -> torch.Tensor:
            if isinstance(model, LatentModel):  # reads the sensors without decoding the whole field where it can
                return model.observe(z, m, rows(z.shape[0]), c)
            fields = model.decode(z, m).flatten(2)[:, c]
            return fields.gather(1, torch.as_tensor(rows(z.shape[0]), device=fields.device))

        if self._coordinate is not None:
            return augment_with_parameter(model.forecast, observe, self._coordinate)
        return LatentDynamics(bind_param(model.forecast, mu), bind_param(observe, mu),
                              forecast_jacobian=model.filter_forecast_jacobian(mu),
                              observe_jacobian=model.filter_observe_jacobian(mu, rows, channel))

    def _parameter_start(self, envs: Sequence[SensingEnv]) -> tuple[float, float] | None:
        """Set the mu the model is run with (and the coordinate of an estimated one); return the estimated
        coordinate's prior (mean, std), None when mu is not estimated."""
        choice = self.config.parameter
        self._true_mu = np.array([e.mu for e in envs], dtype=np.float64)  # for scoring only
        self._coordinate, prior = None, None
        if choice == "known":
            if any(getattr(e, "parameter", "known") == "hidden" for e in envs):
                raise ValueError(f"the env{'s' if len(envs) > 1 else ''} hide{'' if len(envs) > 1 else 's'} mu "
                                 "(parameter='hidden'), so the filter cannot be told it: estimate it with "
                                 "FilterConfig(parameter='estimate') or assume a value with "
                                 "FilterConfig(parameter=VALUE)")
            values = self._true_mu
        elif choice in ("estimate", "prior"):
            train = envs[0].dataset.params("train")
            coordinate, mean, std = self.config.parameter_state(float(np.min(train)), float(np.max(train)))
            values = np.full(len(envs), float(coordinate.to_param(torch.tensor(mean, dtype=torch.float64))))
            if choice == "estimate":
                self._coordinate, prior = coordinate, (mean, std)
                self._prior_std = std
        else:
            values = np.full(len(envs), float(choice))
        self._mu = torch.as_tensor(values, dtype=self.dtype, device=self.device)
        return prior

    @torch_threads("assimilate")
    def start(self, envs: Sequence[SensingEnv], seed: int, sensors: np.ndarray | None = None) -> Snapshot:
        """A fresh filter for the envs' current episodes (call right after resetting them).

        ``sensors`` (B, m): the layouts the filter reads, when they are not the envs' own.
        """
        prior = self._parameter_start(envs)
        self._sensors.current = np.stack([e.sensors for e in envs]) if sensors is None else np.asarray(sensors)
        # A noise-free env (noise_level=0) still needs a positive R for the gain to exist.
        sigma = torch.tensor([max(e.sigma, 1e-12) for e in envs], dtype=self.dtype, device=self.device)
        n_sensors = self._sensors.current.shape[1]
        self._filter = self.config.make(self._dynamics(envs[0].benchmark.observed_channel), sigma, seed, self.model,
                                        n_sensors)
        if self.config.initial == "exact":
            with torch.no_grad():
                z0 = self.model.encode(self._truth(envs), self._mu)
        else:
            z0 = approximate_initial_latent(self.model, envs[0].dataset).expand(len(envs), -1)
        self._filter.reset(*self.config.initial_state(self.model, z0.to(self.device, self.dtype).clone(), sigma,
                                                      n_sensors, prior))
        self._lag, self._k, self._now = _latency(envs), 0, self._filter
        self._ranked = None
        if self.uncertainty and isinstance(self._filter, EnKF):
            bench = envs[0].benchmark
            # Ties of truth and members are broken by a generator of its own: the filter's draws stay as they were.
            self._ranked = (bench.observed_index * bench.n_cells, rank_cells(bench, envs[0].fluid_mask),
                            np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(1,))))
        return self._snapshot(envs)

    @torch_threads("assimilate")
    def step(self, envs: Sequence[SensingEnv], readings: np.ndarray, sensors: np.ndarray) -> Snapshot:
        """Forecast (Eqs. 13-14), update with ``readings`` (B, m) taken at ``sensors`` (B, m) unless this is
        the forward run (Eqs. 15-17), decode the mean and score it against the envs' truth (Eq. 18).

        A missing reading (NaN, as a faulty sensor reports it) is left out of the update; an element with none
        present only forecasts. Late readings (the envs' ``faults.latency`` = d frames) are assimilated at
        their observation time: the filter stays at frame k - d, steps only once k > d (frame 0's reading,
        which arrives at k = d, is the initial frame the filter starts from) and the estimate at frame k is
        its d-step forecast (:meth:`~dks_gym.filters.EKF.lead`)."""
        if self._filter is None:
            raise RuntimeError("call reset() before step()")
        self._sensors.current = np.asarray(sensors)
        self._k += 1
        stepped = self._k > self._lag  # the readings measure frame k - lag >= 1
        if stepped:
            y = torch.as_tensor(np.asarray(readings), dtype=self.dtype, device=self.device)
            present = torch.isfinite(y)
            self._filter.step(y, assimilate=self.config.assimilates, mask=None if bool(present.all()) else present)
        self._now = self._filter.lead(min(self._k, self._lag)) if self._lag else self._filter
        if self._coordinate is not None:  # decode with the current estimate of mu
            self._mu = self._coordinate.to_param(self._now.mean[:, self.model.r].detach())
        return self._snapshot(envs, with_diagnostics=True, stepped=stepped)

    def _truth(self, envs: Sequence[SensingEnv]) -> torch.Tensor:
        return torch.as_tensor(np.stack([e.true_state for e in envs]), dtype=self.dtype, device=self.device)

    def _snapshot(self, envs: Sequence[SensingEnv], with_diagnostics: bool = False,
                  stepped: bool = True) -> Snapshot:
        with torch.no_grad():
            if self.uncertainty and not isinstance(self._now, EnKF):  # diag(G P G^T) from the same decoder pass
                r = self.model.r
                estimate, variance = decoded_variance(self.model, self._latent_mean(), self._mu,
                                                      self._now.cov[:, :r, :r])
            else:
                estimate, variance = self.model.decode(self._latent_mean(), self._mu), None
        truth = self._truth(envs).to(estimate)
        bench = envs[0].benchmark
        std = torch.as_tensor(envs[0].dataset.stats_std, device=estimate.device)
        relative, per_channel = relative_l2_errors(estimate, truth, bench.scored_indices)
        snap = Snapshot(estimate=estimate,
                        mse=field_errors(estimate, truth, bench.scored_indices).cpu().numpy(),
                        normalized_mse=field_errors(estimate, truth, bench.scored_indices, std).cpu().numpy(),
                        relative_l2=relative, channel_relative_l2=per_channel,
                        latent_mean=self._latent_mean().cpu().numpy())
        if self.uncertainty:
            cells = self._checked_cells() if with_diagnostics and self._ranked is not None else None
            snap.estimate_std, members = self._predictive(estimate, cells, variance)
            scores = gaussian_scores(estimate, snap.estimate_std, truth, bench.scored_indices,
                                     envs[0].dataset.stats_std)
            snap.coverage, snap.nees, snap.crps = scores["coverage"], scores["nees"], scores["crps"]
            snap.predicted_mse = scores["predicted_mse"]
            if members is not None:
                at = truth.flatten(1).gather(1, cells)
                ranks = truth_ranks(members.cpu().double().numpy(), at.cpu().double().numpy(), self._ranked[2])
                m = self._sensors.current.shape[1]
                snap.sensor_ranks, snap.cell_ranks = ranks[:, :m], ranks[:, m:]
        if self._coordinate is not None:
            snap.parameter = self.parameter_scores()
        if with_diagnostics and stepped:
            d = self._filter.diagnostics
            snap.diagnostics = {"gain_norm": d.gain_norm[-1].cpu().numpy(), "spread": d.spread[-1].cpu().numpy()}
            if isinstance(self._filter, EKF):  # the EnKF uses no forecast Jacobian
                snap.diagnostics["forecast_norm"] = d.forecast_norm[-1].cpu().numpy()
        elif with_diagnostics:  # waiting for the first late reading: no update, the filter has not stepped
            batch = len(envs)
            snap.diagnostics = {"gain_norm": np.zeros(batch), "spread": np.full(batch, np.nan)}
            if isinstance(self._filter, EKF):
                snap.diagnostics["forecast_norm"] = np.full(batch, np.nan)
        return snap

    @property
    def rank_cells(self) -> np.ndarray | None:
        """The fixed cells the EnKF's rank histograms check (flat indices into (C, *grid),
        :func:`~dks_gym.assimilation.spread.rank_cells`); None for the other filters or without uncertainty."""
        return None if self._ranked is None else self._ranked[1]

    def predictive_std(self, estimate: torch.Tensor | None = None) -> torch.Tensor:
        """The predictive standard deviation of every decoded cell, (B, C, *grid), physical units.

        EKF and forward run: ``sqrt(diag(G P G^T) + reconstruction_var)`` with ``G`` the decoder Jacobian at
        the filter mean; EnKF: ``sqrt(var of the decoded members + reconstruction_var)``. ``estimate``: the
        decoded filter mean, when the caller has it already.
        """
        if self._now is None:
            raise RuntimeError("call start() before predictive_std()")
        return self._predictive(estimate)[0]

    def _checked_cells(self) -> torch.Tensor:
        """(B, m + k) the cells the EnKF's rank histograms check, flat field indices: the sensors read at this
        frame (on the observed channel), then the fixed cells."""
        offset, fixed, _ = self._ranked
        sensors = offset + np.asarray(self._sensors.current, dtype=np.int64)
        cells = np.concatenate([sensors, np.broadcast_to(fixed, (len(sensors), len(fixed)))], axis=1)
        return torch.as_tensor(cells, device=self.device)

    def _predictive(self, estimate: torch.Tensor | None, cells: torch.Tensor | None = None,
                    variance: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor | None]:
        """:meth:`predictive_std` and, for the EnKF with ``cells`` (B, k), its decoded members there (B, n, k).
        ``variance``: the EKF's ``diag(G P G^T)`` when the caller has it (:func:`decoded_variance`)."""
        members = None
        with torch.no_grad():
            r = self.model.r  # the model's part of the state (the rest: estimated sensor biases)
            if estimate is None:
                estimate = self.model.decode(self._latent_mean(), self._mu)
            if isinstance(self._now, EnKF):
                var, members = decoded_ensemble(self.model, self._now.ensemble[..., :r], self._mu, center=estimate,
                                                cells=cells)
            elif variance is not None:
                var = variance
            else:
                var = jacobian_variance(self.model, self._now.mean[:, :r], self._mu, self._now.cov[:, :r, :r])
            var = var.reshape(estimate.shape)  # in place from here: var is this call's own
            if self.reconstruction_var is not None:
                var.add_(self.reconstruction_var.to(var))
            return var.clamp_min_(0.0).sqrt_(), members

    def parameter_scores(self) -> dict[str, np.ndarray]:
        """The estimated mu per element and how it fares (see :attr:`Snapshot.parameter`)."""
        r, coordinate = self.model.r, self._coordinate
        s = self._now.mean[:, r].detach().double()
        s_std = self._now.cov[:, r, r].detach().double().clamp_min(0.0).sqrt()
        mu = coordinate.to_param(s)
        low, high = coordinate.interval(s, s_std)
        truth = torch.as_tensor(self._true_mu, dtype=torch.float64, device=s.device)
        return {"mu_estimate": mu.cpu().numpy(), "mu_std": (mu * s_std if coordinate.log else s_std).cpu().numpy(),
                "mu_low": low.cpu().numpy(), "mu_high": high.cpu().numpy(),
                "mu_out_of_range": coordinate.outside(s).cpu().numpy(),
                "mu_relative_error": ((mu - truth).abs() / truth.abs()).cpu().numpy(),
                "mu_in_interval": ((low <= truth) & (truth <= high)).cpu().numpy(),
                "mu_std_ratio": (s_std / self._prior_std).cpu().numpy()}

    def truth(self, envs: Sequence[SensingEnv]) -> np.ndarray:
        """The envs' true fields (B, C, *grid) as the core scores them, float32."""
        return self._truth(envs).cpu().numpy().astype(np.float32)

    def belief(self) -> np.ndarray:
        """[mean z; log diag P] per element, (B, 2r) float32."""
        r = self.model.r
        var = self._now.cov[:, :r, :r].diagonal(dim1=-2, dim2=-1).clamp_min(1e-30)
        return torch.cat([self._latent_mean(), var.log()], dim=1).cpu().numpy().astype(np.float32)

    def _latent_mean(self) -> torch.Tensor:
        """The model's part of the current mean (B, r), without the estimated sensor biases."""
        return self._now.mean[:, : self.model.r].detach()

    def bias(self) -> np.ndarray | None:
        """The estimated sensor biases (B, m) with ``FilterConfig(bias_drift=...)``, else None."""
        if self.config.bias_drift is None or self._now is None:
            return None
        return self._now.mean[:, self.model.r + (self._coordinate is not None):].detach().cpu().numpy()

    def history(self) -> dict[str, np.ndarray | None]:
        """Over the steps so far: ``forecast_norm`` (n, B) (None for the EnKF), ``step_seconds`` (n,), and
        ``divergence_resets`` (B,), how many times each element was restarted, ``gain_norm`` and ``spread``
        (n, B) (see :class:`~dks_gym.filters.diagnostics.Diagnostics`). With late readings the first steps, while
        the filter waits for its first reading, have gain 0 and NaN spread and forecast norm; ``step_seconds``
        holds the filter's steps only."""
        d = self._filter.diagnostics
        waited = self._k - len(d)

        def padded(name: str, value: float) -> np.ndarray:
            steps = d.stacked(name).cpu().double().numpy() if len(d) else np.empty((0, len(self._filter.mean)))
            return np.concatenate([np.full((waited, steps.shape[1]), value), steps])

        return {"gain_norm": padded("gain_norm", 0.0), "spread": padded("spread", np.nan),
                "forecast_norm": padded("forecast_norm", np.nan) if isinstance(self._filter, EKF) else None,
                "step_seconds": np.asarray(d.wall_time, dtype=np.float64),
                "divergence_resets": d.stacked("reset").sum(0).cpu().numpy().astype(np.int64)}


def _latency(envs: Sequence[SensingEnv]) -> int:
    """The frames by which the envs' readings are late (their faults' latency), the same for every env."""
    lags = {0 if e.faults is None else e.faults.latency for e in envs}
    if len(lags) > 1:
        raise ValueError(f"the envs' readings are late by different numbers of frames {sorted(lags)}; "
                         "one batch needs one latency (give every env the same faults)")
    return lags.pop()


def _check_reconstruction_var(model: FilterableModel, value: Any, device: torch.device,
                              dtype: torch.dtype) -> torch.Tensor:
    """``value`` as a (C, *grid) tensor (a number: the same for every cell), checked: finite, non-negative,
    the model's field shape."""
    t = torch.as_tensor(np.asarray(value.detach().cpu() if isinstance(value, torch.Tensor) else value,
                                   dtype=np.float64))
    expected = (int(model.n_fields), *model.grid) if hasattr(model, "grid") else tuple(t.shape)
    if t.ndim == 0:
        t = t.expand(expected).clone()
    if tuple(t.shape) != expected:
        raise ValueError(f"reconstruction_var must have the decoded field's shape {expected} (C, *grid), "
                         f"got {tuple(t.shape)}; see dks_gym.assimilation.reconstruction_variance")
    if not bool(torch.isfinite(t).all()) or bool((t < 0).any()):
        raise ValueError("reconstruction_var must be finite and non-negative (a variance per cell)")
    return t.to(device=device, dtype=dtype)
