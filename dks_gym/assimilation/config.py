"""How to filter, in one frozen object: :class:`FilterConfig`; and what an evaluation run holds fixed besides it.

:data:`FILTERS` is the one list of filter names: ``"forward"`` is the forward run (the filter loop with the
update switched off), ``"ekf"`` Eqs. 13-17, ``"enkf"`` the stochastic EnKF. :class:`AssimilationConfig`
adds the sensing settings of a batched evaluation run (noise level, sensor count, noise seed, split) to a
:class:`FilterConfig`, without re-declaring its fields.
"""

from __future__ import annotations

import dataclasses
import numbers
import warnings
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from ..dataset import SPLITS
from ..envs.faults import SensorFaults
from ..filters import EKF, EnKF, LatentDynamics, augment_with_bias, augmented_covariance
from ..filters.covariance import as_covariance, check_covariance_spec
from ..filters.enkf import Localization
from ..filters.parameter import ParameterCoordinate
from ..models import FilterableModel
from ..names import FILTERS

INITIAL_CONDITIONS = ("approximate", "exact")
DIVERGENCE_POLICIES = ("raise", "reset")
#: Named choices of Q and P0: the paper's (1e-4 I, 1.0 I), or measured on the model's own errors (calibrated).
CALIBRATION_CHOICES = ("paper", "calibrated")
#: How the filter treats the physical parameter mu: told the env's (``known``), estimates it with the state, or
#: assumes the prior's mean (``prior``: what a filter without the parameter's value would do).
PARAMETER_CHOICES = ("known", "estimate", "prior")
PAPER_Q, PAPER_P0 = 1e-4, 1.0


@dataclass(frozen=True)
class FilterConfig:
    """How to filter (defaults: SPEC section 4), checked when built.

    ``kind``: one of :data:`FILTERS`. ``initial``: "approximate" (mean encoded first frame of the training
    trajectories) or "exact" (the encoded true first frame). ``P0``, ``Q``: initial and process-noise
    covariances (a variance times I, or a (B,), (r, r) or (B, r, r) tensor), or by name: "paper" (Q = 1e-4 I,
    P0 = I, the paper's) or "calibrated" (measured on the model's own errors when it was trained,
    ``model.calibration``: Q its latent one-step residual covariance on held-out trajectories, times the scale
    that makes the EKF's 95 % intervals cover 95 % of those trajectories (``calibration["Q_scale"]``,
    :func:`~dks_gym.assimilation.ensure_process_noise_scale`; 1 until tuned), P0 the spread
    of the encoded first frames around the approximate initial condition, or Q for the exact one). The
    default is "calibrated": with the paper's values a converged model's EKF is worse than its forward run
    (docs/filters.md). R = sigma^2 I comes from the env. EnKF: ``n_members``, ``inflation`` (multiplicative,
    1 = none), ``localization`` (a hook
    ``(C_zy, C_yy) -> (C_zy, C_yy)``, e.g. :func:`~dks_gym.filters.schur_localization`).
    ``on_divergence``: "raise" stops at a non-finite estimate, "reset" restarts the diverged elements.
    ``seed``: seeds the EnKF's draws when the caller gives none.
    ``bias_drift``: estimate each sensor's bias with the state (:func:`~dks_gym.filters.augment_with_bias`,
    docs/filters.md): the standard deviation of the bias random walk's step per frame, in the observed
    channel's units (0: a constant unknown bias); None (default): no bias. ``bias_prior``: the initial bias's
    standard deviation (default: the env's noise sigma). The bias belongs to a sensor slot of the layout.
    ``parameter``: "known" (default: the env's true mu), "estimate" (mu joins the state,
    :mod:`dks_gym.filters.parameter`, docs/filters.md), "prior" (mu assumed at the prior's mean) or a number
    (mu assumed to be that value). ``parameter_prior``: with "estimate" or "prior", the prior ``(mean, std)``
    of mu in its physical units (default: the mean and std of a uniform over the training range, in the
    estimated coordinate); ``parameter_drift``: the std of the estimated
    coordinate's random-walk step per frame (log mu where the training range spans a decade: a relative
    change), None or 0 for a constant parameter.
    """

    kind: str = "ekf"
    initial: str = "approximate"
    P0: float | str | torch.Tensor = "calibrated"
    Q: float | str | torch.Tensor = "calibrated"
    n_members: int = 20
    inflation: float = 1.0
    localization: Localization | None = None
    on_divergence: str = "raise"
    seed: int = 0
    bias_drift: float | None = None
    bias_prior: float | None = None
    parameter: str | float = "known"
    parameter_prior: tuple[float, float] | None = None
    parameter_drift: float | None = None

    def __post_init__(self) -> None:
        if self.kind not in FILTERS:
            hint = " (the forward run is called 'forward')" if self.kind == "none" else ""
            raise ValueError(f"unknown filter {self.kind!r}{hint}; choose one of {', '.join(FILTERS)}")
        if self.initial not in INITIAL_CONDITIONS:
            raise ValueError(f"unknown initial condition {self.initial!r}; choose 'approximate' or 'exact'")
        for name, definite in (("P0", True), ("Q", False)):
            value = getattr(self, name)
            if isinstance(value, str):
                if value not in CALIBRATION_CHOICES:
                    raise ValueError(f"{name} must be a covariance or one of "
                                     f"{', '.join(map(repr, CALIBRATION_CHOICES))}, got {value!r}")
            else:
                check_covariance_spec(value, name, definite=definite)
        n = self.n_members
        if isinstance(n, bool) or not isinstance(n, numbers.Integral) or n < 2:
            raise ValueError(f"n_members must be an integer >= 2 (an ensemble needs two members "
                             f"for a covariance), got {n!r}")
        inflation = self.inflation
        if isinstance(inflation, bool) or not isinstance(inflation, numbers.Real) \
                or not (1.0 <= float(inflation) < float("inf")):
            raise ValueError(f"inflation must be a finite factor >= 1 (1.0 = none), got {inflation!r}")
        if self.localization is not None and not callable(self.localization):
            raise ValueError("localization must be a callable (C_zy, C_yy) -> (C_zy, C_yy), "
                             "e.g. dks_gym.filters.schur_localization(rho)")
        if self.on_divergence not in DIVERGENCE_POLICIES:
            raise ValueError(f"on_divergence must be 'raise' or 'reset', got {self.on_divergence!r}")
        if isinstance(self.seed, bool) or not isinstance(self.seed, numbers.Integral):
            raise ValueError(f"seed must be an integer, got {self.seed!r}")
        for name, low in (("bias_drift", 0.0), ("bias_prior", None)):
            value = getattr(self, name)
            if value is None:
                continue
            if isinstance(value, bool) or not isinstance(value, numbers.Real) or not np.isfinite(value) \
                    or (value < 0 if low is not None else value <= 0):
                bound = ">= 0" if low is not None else "> 0"
                raise ValueError(f"{name} must be a finite standard deviation {bound} (observed channel's units) "
                                 f"or None, got {value!r}")
        if self.bias_prior is not None and self.bias_drift is None:
            raise ValueError("bias_prior is the initial bias of the estimated sensor biases: set bias_drift too "
                             "(0.0 for a constant bias)")
        self._check_parameter()

    def _check_parameter(self) -> None:
        p = self.parameter
        if isinstance(p, str):
            if p not in PARAMETER_CHOICES:
                raise ValueError(f"parameter must be 'known', 'estimate' or a number (an assumed mu), got {p!r}")
        elif isinstance(p, bool) or not isinstance(p, numbers.Real) or not np.isfinite(p):
            raise ValueError(f"parameter must be 'known', 'estimate' or a finite number (an assumed mu), got {p!r}")
        estimating = p == "estimate"
        if self.parameter_prior is not None:
            if p not in ("estimate", "prior"):
                raise ValueError("parameter_prior is the prior of an estimated mu: set parameter='estimate' (or "
                                 "'prior', its mean assumed) too")
            prior = self.parameter_prior
            if not (isinstance(prior, (tuple, list)) and len(prior) == 2 and all(
                    isinstance(v, numbers.Real) and not isinstance(v, bool) and np.isfinite(v) for v in prior)):
                raise ValueError(f"parameter_prior must be (mean, std), two finite numbers in mu's units, "
                                 f"got {prior!r}")
            if prior[1] <= 0:
                raise ValueError(f"parameter_prior's std must be > 0 (a Gaussian prior of mu), got {prior[1]!r}")
            object.__setattr__(self, "parameter_prior", (float(prior[0]), float(prior[1])))
        drift = self.parameter_drift
        if drift is not None:
            if not estimating:
                raise ValueError("parameter_drift is the random walk of an estimated mu: set parameter='estimate'")
            if isinstance(drift, bool) or not isinstance(drift, numbers.Real) or not np.isfinite(drift) or drift < 0:
                raise ValueError(f"parameter_drift must be a finite standard deviation >= 0 per frame or None, "
                                 f"got {drift!r}")

    @property
    def estimates_parameter(self) -> bool:
        """Whether mu is part of the filter's state."""
        return self.parameter == "estimate"

    def parameter_state(self, low: float, high: float) -> tuple[ParameterCoordinate, float, float]:
        """For an estimated mu with the training range ``[low, high]``: its coordinate and the prior (mean, std)
        of that coordinate; a ValueError when a given prior's mean lies outside the range or is not positive
        where mu is estimated in log."""
        coordinate = ParameterCoordinate.for_range(low, high)
        if self.parameter_prior is None:
            return (coordinate, *coordinate.prior())
        mean, std = self.parameter_prior
        if not low <= mean <= high:
            raise ValueError(f"parameter_prior's mean {mean:g} lies outside the training range [{low:g}, {high:g}] "
                             "of the parameter: the model was not trained there; give a mean inside it")
        return (coordinate, *coordinate.prior(mean, std))

    @property
    def assimilates(self) -> bool:
        """False for the forward run."""
        return self.kind != "forward"

    def process_noise(self, model: FilterableModel) -> float | torch.Tensor:
        """``Q`` as the filters take it, a named choice resolved for ``model``."""
        if isinstance(self.Q, str):
            if self.Q == "paper":
                return PAPER_Q
            # The residual covariance times the scale tuned on held-out coverage (tuning.tune_process_noise).
            return _calibrated(model, "Q") * process_noise_scale(model)
        return self.Q

    def initial_covariance(self, model: FilterableModel) -> float | torch.Tensor:
        """``P0`` as the filters take it, a named choice resolved for ``model`` and the initial condition."""
        if isinstance(self.P0, str):
            if self.P0 == "paper":
                return PAPER_P0
            return _calibrated(model, "P0_exact" if self.initial == "exact" else "P0")
        return self.P0

    def make(self, dynamics: LatentDynamics, sigma: torch.Tensor, seed: int,
             model: FilterableModel | None = None, n_sensors: int | None = None) -> EKF | EnKF:
        """The filter object (the forward run is the EKF loop stepped with the update off); ``model``
        resolves ``Q="calibrated"``. With ``bias_drift`` the state is ``[z; b]`` over ``n_sensors`` biases; with an
        estimated parameter ``dynamics`` are those of ``[z; s]`` and the state ``[z; s; b]``."""
        Q = self.process_noise(model)  # the filters convert it to the state's dtype and device
        r = model.r
        if self.estimates_parameter:  # the dynamics come augmented with [z; s] (core), Q gets the s block
            Q = augmented_covariance(Q, r, 1, float(self.parameter_drift or 0.0) ** 2)
            r += 1
        if self.bias_drift is not None:
            dynamics = augment_with_bias(dynamics, n_sensors)
            Q = augmented_covariance(Q, r, n_sensors, float(self.bias_drift) ** 2)
        if self.kind == "enkf":
            return EnKF(dynamics, sigma=sigma, Q=Q, n_members=self.n_members, inflation=self.inflation,
                        localization=self.localization, generator=seed, on_divergence=self.on_divergence)
        return EKF(dynamics, sigma=sigma, Q=Q, on_divergence=self.on_divergence)

    def initial_state(self, model: FilterableModel, z0: torch.Tensor, sigma: torch.Tensor,
                      n_sensors: int, parameter_prior: tuple[float, float] | None = None,
                      ) -> tuple[torch.Tensor, torch.Tensor | float]:
        """The filter's start ``(mean, P0)``: ``z0`` and :meth:`initial_covariance`, augmented with the estimated
        parameter's prior (mean, std) of its coordinate when given, and with zero biases of variance
        ``bias_prior**2`` (default ``sigma**2`` per element) when ``bias_drift`` is set."""
        P0 = self.initial_covariance(model)
        if parameter_prior is not None:
            batch, r = z0.shape
            P = torch.zeros(batch, r + 1, r + 1, dtype=z0.dtype, device=z0.device)
            P[:, :r, :r] = as_covariance(P0, batch, r, like=z0, name="P0")
            P[:, r, r] = parameter_prior[1] ** 2
            z0, P0 = torch.cat([z0, z0.new_full((batch, 1), parameter_prior[0])], dim=1), P
        if self.bias_drift is None:
            return z0, P0
        batch, r = z0.shape
        prior = sigma if self.bias_prior is None else torch.full_like(sigma, float(self.bias_prior))
        P = torch.zeros(batch, r + n_sensors, r + n_sensors, dtype=z0.dtype, device=z0.device)
        P[:, :r, :r] = as_covariance(P0, batch, r, like=z0, name="P0")
        P[:, r:, r:] = torch.diag_embed((prior.to(z0) ** 2)[:, None].expand(batch, n_sensors))
        return torch.cat([z0, z0.new_zeros(batch, n_sensors)], dim=1), P


_UNTUNED_WARNED: set[tuple[str, str, str]] = set()


def process_noise_scale(model: FilterableModel) -> float:
    """The scale of the model's calibrated Q (``calibration["Q_scale"]``, tuned at the end of training).

    A model without one runs with the unscaled calibrated Q and warns once per model, naming the command
    that tunes it: nothing is tuned or written here."""
    calibration = getattr(model, "calibration", None) or {}
    if "Q_scale" in calibration:
        return float(calibration["Q_scale"])
    benchmark, kind = str(getattr(model, "benchmark", "")), str(getattr(model, "kind", ""))
    key = (benchmark, kind, str(getattr(model, "checkpoint_path", id(model))))
    if key not in _UNTUNED_WARNED:
        _UNTUNED_WARNED.add(key)
        warnings.warn(f"this {benchmark} {kind} model has no tuned process-noise scale: its calibrated Q is used "
                      f"unscaled, so estimate_std may be too narrow or too wide. Tune it once with `dks-gym "
                      f"calibrate {benchmark or 'BENCHMARK'} --model {kind or 'KIND'}`", stacklevel=3)
    return 1.0


def _calibrated(model: FilterableModel, name: str) -> torch.Tensor:
    value = getattr(model, "calibration", {}).get(name)
    if value is None:
        raise ValueError(
            f"this {getattr(model, 'kind', '')} model has no calibrated {name} (it was trained by an older dks-gym, "
            "or built without training): retrain it (`dks-gym train ... --restart`, or load_model(..., "
            "train_if_missing=True) for a cached one), or set Q='paper' and P0='paper' (the paper's 1e-4 I and I) "
            "or your own values in the FilterConfig")
    return value


@dataclass(frozen=True)
class AssimilationConfig:
    """An evaluation run's settings: a :class:`FilterConfig` plus how the episodes are sensed.

    ``filter``: the filter settings (default: the paper's EKF, restarting diverged trajectories);
    ``noise_level``: sigma as a fraction of max |observed channel|; ``n_sensors``: sensors per layout;
    ``noise_seed``: seed of the measurement noise, shared by every model and filter; ``split``: the
    dataset split the episodes come from; ``faults``: the sensors' faults
    (:class:`~dks_gym.envs.SensorFaults` or a dict of its fields; None: none).
    """

    filter: FilterConfig = field(default_factory=lambda: FilterConfig(on_divergence="reset"))
    noise_level: float = 0.2
    n_sensors: int = 16
    noise_seed: int = 0
    split: str = "test"
    faults: SensorFaults | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.filter, FilterConfig):
            raise TypeError(f"AssimilationConfig.filter must be a FilterConfig, got {type(self.filter).__name__}; "
                            "use config.replace(kind='enkf', ...) to change a filter setting")
        if not (np.isfinite(self.noise_level) and self.noise_level > 0):
            raise ValueError(
                f"noise_level must be a positive fraction of the observed channel's maximum (e.g. 0.2), "
                f"got {self.noise_level!r}"
            )
        if int(self.n_sensors) != self.n_sensors or self.n_sensors < 1:
            raise ValueError(f"n_sensors must be a positive integer, got {self.n_sensors!r}")
        if self.split not in SPLITS:
            raise ValueError(f"unknown split {self.split!r}; choose 'train' or 'test'")
        object.__setattr__(self, "faults", SensorFaults.from_any(self.faults))

    def replace(self, **changes: Any) -> "AssimilationConfig":
        """A copy with fields of this config or of its :class:`FilterConfig` changed (``kind="enkf"``,
        ``noise_level=0.1``)."""
        own = {f.name for f in dataclasses.fields(self)} - {"filter"}
        filter_fields = {f.name for f in dataclasses.fields(FilterConfig)}
        unknown = set(changes) - own - filter_fields - {"filter"}
        if unknown:
            raise TypeError(f"unknown setting(s) {', '.join(sorted(unknown))}; AssimilationConfig has "
                            f"{', '.join(sorted(own))} and FilterConfig has {', '.join(sorted(filter_fields))}")
        filter_config = changes.pop("filter", self.filter)
        nested = {k: changes.pop(k) for k in list(changes) if k in filter_fields}
        if nested:
            filter_config = dataclasses.replace(filter_config, **nested)
        return dataclasses.replace(self, filter=filter_config, **changes)

    def as_record(self) -> dict[str, Any]:
        """The flat, JSON-ready settings stored in results files (the filter's kind under ``"filter"``)."""
        f = self.filter
        return {"filter": f.kind, "initial": f.initial, "noise_level": self.noise_level, "n_members": f.n_members,
                "n_sensors": self.n_sensors, "P0": _plain(f.P0), "Q": _plain(f.Q), "noise_seed": self.noise_seed,
                "filter_seed": f.seed, "split": self.split, "on_divergence": f.on_divergence,
                "bias_drift": f.bias_drift, "bias_prior": f.bias_prior,
                "faults": None if self.faults is None else dataclasses.asdict(self.faults),
                # a known mu, the default, adds nothing (files made before the option read the same)
                **({} if f.parameter == "known" else {"parameter": f.parameter, "parameter_drift": f.parameter_drift,
                                                      "parameter_prior": _plain_prior(f.parameter_prior)})}


def _plain_prior(prior: tuple[float, float] | None) -> list[float] | None:
    return None if prior is None else list(prior)


def _plain(value: float | torch.Tensor) -> Any:
    return value.tolist() if isinstance(value, torch.Tensor) else value
