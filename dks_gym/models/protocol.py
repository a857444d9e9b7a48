"""What the assimilation core needs of a latent model, as a :class:`typing.Protocol`: :class:`FilterableModel`.

The four model classes (Koopman, pDMD, MLP, xLSTM) satisfy it by inheriting from
:class:`~dks_gym.models.LatentModel`; a model of your own satisfies it by having these members, whatever its
base class. Exactly these are read by :mod:`dks_gym.assimilation` and the wrappers; the optional extras
they use when present (``grid`` and ``n_fields`` to size a decoded field without decoding one, a
``decoder_variance`` for an exact, fast predictive std, ``decode_with_variance`` to decode the estimate and
push its covariance through one forward pass, ``checkpoint_path`` to store a tuned Q scale) are not part
of it. :func:`model_device` and :func:`model_dtype` read where any model's tensors live.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Protocol, runtime_checkable

import numpy as np
import torch

from .presets import BenchmarkShape

#: A map over a batch of latent states, as the filters take a Jacobian: (n, r) -> (n, ...).
LatentMap = Callable[[torch.Tensor], Any]


@runtime_checkable
class FilterableModel(Protocol):
    """A latent model the EKF, EnKF and forward run can follow (batched over a leading dimension B).

    ``benchmark`` (its name) and ``shape`` (its grid and channel names) tie it to one benchmark; ``r`` is
    the latent dimension, ``kind`` its name in tables ("koopman", "pdmd", "mlp", "xlstm" or your own);
    ``calibration``: what was measured on its own errors ("Q", "P0", "P0_exact", "Q_scale",
    "reconstruction_variance"; empty: give Q and P0 in the :class:`~dks_gym.FilterConfig`).
    ``isinstance(obj, FilterableModel)`` checks that the members exist, not their signatures.
    """

    benchmark: str
    kind: str
    r: int
    shape: BenchmarkShape
    calibration: dict[str, torch.Tensor]

    def encode(self, x: Any, mu: Any) -> torch.Tensor:
        """Physical fields (B, C, *grid) -> latent states (B, r)."""

    def decode(self, z: Any, mu: Any) -> torch.Tensor:
        """Latent states (B, r) -> physical fields (B, C, *grid)."""

    def forecast(self, z: Any, mu: Any) -> torch.Tensor:
        """One latent step z_k (B, r) -> z_{k+1} (B, r) (Eq. 5)."""

    def filter_forecast_jacobian(self, mu: torch.Tensor) -> torch.Tensor | LatentMap:
        """dF/dz with ``mu`` (B,) bound: a constant (B, r, r) or a callable over stacked rows."""

    def filter_observe_jacobian(self, mu: torch.Tensor, sensor_rows: Callable[[int], np.ndarray],
                                channel: str) -> LatentMap | None:
        """dh/dz of h(z) = S(decode(z)) with ``mu`` bound: a callable, or None for autodiff."""


#: The members every :class:`FilterableModel` has, read off the class (``typing.get_protocol_members`` is 3.13+).
FILTERABLE_MEMBERS: tuple[str, ...] = (
    *FilterableModel.__annotations__,
    *(name for name, value in vars(FilterableModel).items() if callable(value) and not name.startswith("_")),
)


def missing_members(model: Any) -> list[str]:
    """The :data:`FILTERABLE_MEMBERS` that ``model`` lacks (empty for a :class:`FilterableModel`)."""
    return [name for name in FILTERABLE_MEMBERS if not hasattr(model, name)]


def model_device(model: Any) -> torch.device:
    """The device a model's buffers live on (CPU for a model without tensors)."""
    tensor = _first_tensor(model)
    return tensor.device if tensor is not None else torch.device("cpu")


def model_dtype(model: Any) -> torch.dtype:
    """The floating dtype of a model's buffers (float32 for a model without floating tensors)."""
    tensor = _first_tensor(model)
    return tensor.dtype if tensor is not None and tensor.is_floating_point() else torch.float32


def _first_tensor(model: Any) -> torch.Tensor | None:
    """The normalization buffer ``stats_mean``, else the first parameter, else None."""
    buffer = getattr(model, "stats_mean", None)
    if isinstance(buffer, torch.Tensor):
        return buffer
    return next(iter(model.parameters()), None) if hasattr(model, "parameters") else None
