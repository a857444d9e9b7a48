"""What both filter wrappers build from their arguments: the assimilation core and the belief space.

A wrapper takes a model (a kind name, a :class:`~dks_gym.models.ModelSpec` or a model object), a filter
and its :class:`~dks_gym.FilterConfig`, a reward and the uncertainty option (``True``, ``False`` or an
:class:`Uncertainty`); how a named model is looked up lives in the spec alone. The keywords the wrappers
took before (``r``, ``model_preset``, ``T``, ``device``, ``dtype``, ``train_if_missing``,
``reconstruction_var``) are refused with a TypeError that says where each went.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, TypeVar

import numpy as np
from gymnasium import spaces

from ..assimilation import Assimilation, FilterConfig, ModelLike, resolve_model
from ..envs.sensing import SensingEnv

REWARDS = ("mse", "normalized_mse")

#: The wrappers' former model-loading keywords, and what replaces each.
MOVED_KEYWORDS = {
    "r": "model=ModelSpec(kind, r=...)",
    "model_preset": "model=ModelSpec(kind, preset=...)",
    "T": "model=ModelSpec(kind, T=...)",
    "device": "model=ModelSpec(kind, device=...) (the filter runs on the model's device)",
    "train_if_missing": "model=ModelSpec(kind, train_if_missing=True)",
    "dtype": "a model in that dtype, e.g. model=load_model(...).double() (the filter runs in the model's dtype)",
    "reconstruction_var": "uncertainty=Uncertainty(reconstruction_var=...)",
}

Init = TypeVar("Init", bound=Callable[..., None])


@dataclass(frozen=True, eq=False)
class Uncertainty:
    """The predictive std switched on (``uncertainty=True`` is ``Uncertainty()``), with its options.

    ``reconstruction_var``: the decoder's reconstruction-error variance per cell, ``(C, *grid)`` in physical
    units squared (:func:`~dks_gym.assimilation.reconstruction_variance`) or one number for every cell,
    added to the filter's variance; None (default): the model's calibrated one, else zero; 0: none.
    """

    reconstruction_var: Any = None


def uncertainty_option(option: bool | Uncertainty) -> Uncertainty | None:
    """A wrapper's ``uncertainty`` argument as an :class:`Uncertainty`, or None when it is off."""
    if isinstance(option, Uncertainty):
        return option
    if isinstance(option, (bool, np.bool_)):
        return Uncertainty() if option else None
    raise TypeError(f"uncertainty must be True, False or Uncertainty(reconstruction_var=...), got {option!r}")


def refuses_moved_keywords(init: Init) -> Init:
    """Wrap a wrapper's ``__init__`` so that a former model-loading keyword raises a TypeError naming its
    replacement (the signature stays the wrapped one's)."""

    @functools.wraps(init)
    def checked(self: Any, *args: Any, **kwargs: Any) -> None:
        moved = [name for name in kwargs if name in MOVED_KEYWORDS]
        if moved:
            where = "; ".join(f"{name}= -> {MOVED_KEYWORDS[name]}" for name in moved)
            raise TypeError(f"{type(self).__name__} takes a model, not model-loading keywords: {where} "
                            "(ModelSpec from dks_gym.models, Uncertainty from dks_gym.wrappers; or pass a "
                            "model from dks_gym.load_model(...))")
        init(self, *args, **kwargs)

    return checked  # type: ignore[return-value]


def build_assimilation(base: SensingEnv, model: ModelLike, filter: str | None, config: FilterConfig | None, *,
                       reward: str, uncertainty: bool | Uncertainty = True) -> Assimilation:
    """The assimilation core a filter wrapper runs: the model resolved for the env's dataset (on its device and
    in its dtype), the config with ``filter`` (when given) as its kind. Shared by both wrappers."""
    if reward not in REWARDS:
        raise ValueError(f"unknown reward {reward!r}; choose one of {', '.join(REWARDS)}")
    option = uncertainty_option(uncertainty)
    config = FilterConfig() if config is None else config
    if not isinstance(config, FilterConfig):
        raise TypeError(f"config must be a dks_gym.FilterConfig, got {type(config).__name__}")
    if filter is not None:
        config = dataclasses.replace(config, kind=filter)
    latent = resolve_model(model, base.benchmark.name, base.dataset)
    return Assimilation(latent, config, uncertainty=option is not None,
                        reconstruction_var=None if option is None else option.reconstruction_var)


def belief_space(r: int) -> spaces.Box:
    """The belief [mean z (r); log diag P (r)] as a float32 Box."""
    big = np.finfo(np.float32).max
    return spaces.Box(-big, big, shape=(2 * r,), dtype=np.float32)
