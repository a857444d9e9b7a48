"""Latent-space data-assimilation filters (paper Section II.E and Section IV.D, SPEC section 4).

Model-independent and batched: a model enters only as a :class:`LatentDynamics` of callables over
``(B, r)`` latent tensors. Step functions (:func:`ekf_forecast`, :func:`ekf_update`,
:func:`enkf_forecast`, :func:`enkf_update`) and stateful classes (:class:`EKF`, :class:`EnKF`) with
``reset(z0, P0)`` / ``step(y, assimilate=True, mask=None)`` / ``mean`` / ``cov`` / ``diagnostics``;
:func:`augment_with_bias` estimates sensor biases with the state.
"""

from .bias import augment_with_bias, augmented_covariance
from .covariance import as_covariance
from .diagnostics import Diagnostics
from .divergence import FilterDivergence
from .dynamics import GaussianState, LatentDynamics, bind_param
from .ekf import EKF, ekf_forecast, ekf_update
from .enkf import EnKF, enkf_forecast, enkf_update, ensemble_state, initial_ensemble, schur_localization
from .jacobians import value_and_jacobian

__all__ = [
    "EKF",
    "Diagnostics",
    "EnKF",
    "FilterDivergence",
    "GaussianState",
    "LatentDynamics",
    "as_covariance",
    "augment_with_bias",
    "augmented_covariance",
    "bind_param",
    "ekf_forecast",
    "ekf_update",
    "enkf_forecast",
    "enkf_update",
    "ensemble_state",
    "initial_ensemble",
    "schur_localization",
    "value_and_jacobian",
]
