"""Parametric DMD baseline (Appendix A.1): global POD basis, monolithic DMD, RBF interpolation in mu.

Offline fit, in three steps:

1. A rank-r POD basis U_r of the normalized training snapshots (per-channel train statistics, the
   cell type excluded, no temporal mean removed), computed by :func:`streamed_pod`, a randomized SVD
   whose matrix products stream over one trajectory at a time. It never forms the N x M snapshot
   matrix: the sphere (N = 4 * 64^3 = 1,048,576, M = 90 * 100 = 9,000) needs the two N x (r + p)
   float64 range-finder blocks (p = 10: 2 x 352 MB), one trajectory (420 MB read as float32, 840 MB
   as float64, plus its normalized copy) and a (r + p) x M block, about 3 GB at peak, against 38 GB
   for the dense float32 matrix (75 GB in float64). With q power iterations it reads the data
   2 + q times (default q = 2).
2. PyDMD's ``ParametricDMD`` in its monolithic form (one ``DMD(svd_rank=r)`` on the stacked
   coefficient matrix) with a multiquadric RBF interpolant in mu, :class:`~dks_gym.models.rbf.MultiquadricRBF`:
   scipy's ``RBFInterpolator`` called exactly as ezyrb's ``RBF(kernel="multiquadric")`` calls it (same
   default shape parameter), so the predictions equal ezyrb's without installing it. (ezyrb's own default
   kernel is thin-plate spline despite its docstring.) Its spatial reduction is the identity because it
   receives the POD coefficients U_r^T X of step 1, which is exactly what ``ParametricDMD`` computes with
   an ezyrb ``POD`` of rank r, without handing it the dense snapshots.
3. Online, at a parameter mu, the interpolated coefficients z_k(mu) (Eq. A3) give the one-step
   operator A~(mu) = Z_{1:} Z_{:-1}^+ (Eq. A4), cached per mu. The forecast is A~(mu) z.

Three ill-conditioned solves sit in that chain (on the paper-preset Burgers data at r = 32: the stacked
coefficients have condition number ~3e9, the RBF kernel matrix ~3e18, Z_{:-1}(mu) ~1e8). Solved exactly,
the RBF's and the cutoff of Eq. A4 moved with round-off, so that the fit and the forward run changed with
the thread count and the BLAS build. Each is regularized by a rule relative to its own scale, far above
round-off (float64 eps ~2e-16) and at or below the data's own precision, so that results change
continuously with the data instead of jumping with the rounding:

* ``dmd_tikhonov`` (default 1e-8): PyDMD's own Tikhonov option of the DMD, set so that its filter is
  s / (s^2 + lambda^2) with lambda = ``dmd_tikhonov`` times the largest singular value of the stacked
  coefficients (which reach the float32 data's noise floor near 5e-10 on Burgers);
* ``rbf_smoothing`` (default 1e-10): the RBF's ridge (scipy's ``smoothing``), relative to the norm of the
  kernel matrix on the zero-sum weights the interpolant uses (:func:`~dks_gym.models.rbf.kernel_scale`);
* ``operator_tikhonov`` (default 1e-4): Eq. A4 as the Tikhonov least-squares problem
  min_A ||Z_{1:} - A Z_{:-1}||^2 + lambda^2 ||A||^2, lambda = ``operator_tikhonov`` times the largest
  singular value of Z_{:-1}(mu), about the relative error of the interpolated coefficients (1e-4 to 3e-4
  on Burgers). ``pinv_rtol`` (default None) replaces it by the paper's truncated pseudoinverse with that
  relative cutoff.

The four settings are the model's state: they round-trip through ``state_dict`` (as its extra state) and
are mirrored in the checkpoint metadata. The POD basis vectors get a fixed sign (see
:func:`~dks_gym.models.pod.streamed_pod`), since LAPACK's choice of sign depends on the thread count and the CPU.

As a latent model: encode(x) = U_r^T normalize(x), decode(z) = denormalize(U_r z), both independent of
mu; h(z) = S decode(z) is affine with Jacobian S diag(std) U_r (:meth:`PDMD.observation_matrix`).
"""

from __future__ import annotations

import math
import re
import warnings
from typing import Any, Callable

import numpy as np
import torch

from ..dataset import Dataset
from ..threads import one_blas_thread
from .latent_model import ArrayLike, LatentModel
from .pod import streamed_pod
from .presets import BenchmarkShape

#: PyDMD's warning about the condition number of the snapshots it fits (pydmd/snapshots.py).
_CONDITION_WARNING = re.compile(r"Input data condition number ([-+]?[0-9]*\.?[0-9]+(?:[eE][-+]?[0-9]+)?)")
#: Numbers per chunk of the decoded variance's matrix product (cells x elements x columns): 16 MB in float32.
_CHUNK_NUMBERS = 2**22


class _ReducedCoordinates:
    """Identity reduction for ``ParametricDMD``: its input already is the POD coefficients U_r^T X."""

    def fit(self, x: np.ndarray) -> "_ReducedCoordinates":
        return self

    def reduce(self, x: np.ndarray) -> np.ndarray:
        return x

    def expand(self, x: np.ndarray) -> np.ndarray:
        return x


#: Default regularization of the three ill-conditioned solves (see the module docstring and docs/models.md).
DMD_TIKHONOV = 1e-8
RBF_SMOOTHING = 1e-10
#: Settings that differ from the defaults on one benchmark's data, with the measurement behind each
#: (docs/models.md, pDMD). The dambreak's 90 viscosities: with ``rbf_smoothing`` 1e-10 the test split's
#: forward-run final MSE was 434 / 506 (1 / 2 threads) and 425 / 423 (OpenBLAS Prescott / Sandybridge
#: kernels), the interpolated coefficients 3.6 % apart between 1 and 2 threads; with 1e-8, 440.3 / 440.2
#: and 440.3 / 439.9 (spread 9e-4).
BENCHMARK_SETTINGS: dict[str, dict[str, float]] = {"dambreak": {"rbf_smoothing": 1e-8}}
OPERATOR_TIKHONOV = 1e-4


class _Setting:
    """A regularization setting of :class:`PDMD`: a float in [0, 1) (or None where allowed), validated on
    assignment; changing it drops what was computed with the old value (the DMD fit or the cached A~)."""

    def __init__(self, refits_dmd: bool, optional: bool = False) -> None:
        self.refits_dmd, self.optional = refits_dmd, optional

    def __set_name__(self, owner: type, name: str) -> None:
        self.name = name

    def __get__(self, obj: Any, owner: type) -> Any:
        return self if obj is None else obj.__dict__["_settings"][self.name]

    def __set__(self, obj: Any, value: Any) -> None:
        if value is None and self.optional:
            pass
        elif value is None or not 0 <= float(value) < 1:
            raise ValueError(f"{self.name} must be in [0, 1){' or None' if self.optional else ''}, got {value}")
        else:
            value = float(value)
        settings = obj.__dict__.setdefault("_settings", {})
        if settings.get(self.name, object()) != value:
            settings[self.name] = value
            if "_operator_cache" in obj.__dict__:
                if self.refits_dmd:
                    obj._reset_dmd()
                obj._operator_cache.clear()


class PDMD(LatentModel):
    """Parametric DMD as a latent model (state z = POD coefficients, forecast A~(mu) z).

    Fit with :meth:`fit` on arrays ``(n_traj, n_t, C, *grid)`` in physical units (numpy arrays, torch
    tensors or a lazily read h5py dataset: trajectories are read one at a time), or :meth:`fit_dataset`.
    The regularization settings ``dmd_tikhonov``, ``rbf_smoothing``, ``operator_tikhonov`` and
    ``pinv_rtol`` (module docstring) are constructor arguments and assignable attributes.
    """

    kind = "pdmd"
    fitted_in_closed_form = True
    _RESIZABLE = ("basis", "singular_values", "train_coefficients", "train_params")
    _SETTINGS = ("dmd_tikhonov", "rbf_smoothing", "operator_tikhonov", "pinv_rtol")

    dmd_tikhonov = _Setting(refits_dmd=True)
    rbf_smoothing = _Setting(refits_dmd=True)
    operator_tikhonov = _Setting(refits_dmd=False)
    pinv_rtol = _Setting(refits_dmd=False, optional=True)

    def __init__(
        self,
        shape: BenchmarkShape,
        r: int = 32,
        *,
        dt: float | None = None,
        stats_mean: ArrayLike | None = None,
        stats_std: ArrayLike | None = None,
        dmd_tikhonov: float = DMD_TIKHONOV,
        rbf_smoothing: float = RBF_SMOOTHING,
        operator_tikhonov: float = OPERATOR_TIKHONOV,
        pinv_rtol: float | None = None,
    ) -> None:
        super().__init__(shape, r, dt=dt, stats_mean=stats_mean, stats_std=stats_std)
        self.dmd_tikhonov = dmd_tikhonov
        self.rbf_smoothing = rbf_smoothing
        self.operator_tikhonov = operator_tikhonov
        self.pinv_rtol = pinv_rtol
        self.n_state = self.n_fields * math.prod(self.grid)
        self.register_buffer("basis", torch.zeros(0, self.r))  # U_r (N, r), normalized units
        self.register_buffer("singular_values", torch.zeros(0, dtype=torch.float64))
        self.register_buffer("train_coefficients", torch.zeros(0, 0, self.r, dtype=torch.float64))
        self.register_buffer("train_params", torch.zeros(0, dtype=torch.float64))
        self.fit_info: dict[str, Any] = {}
        self._pdmd: Any = None
        # PyDMD's condition number of the stacked coefficients when it exceeds 1e5 (see parametric_dmd).
        self.dmd_condition_number: float | None = None
        self._operator_cache: dict[float, np.ndarray] = {}
        self._forecast_cache: torch.Tensor | None = None  # see _forecast_training_coefficients

    @property
    def settings(self) -> dict[str, float | None]:
        """The regularization settings, by name."""
        return {name: getattr(self, name) for name in self._SETTINGS}

    @property
    def is_fitted(self) -> bool:
        return self.basis.shape[0] == self.n_state

    def _require_fitted(self) -> None:
        if not self.is_fitted:
            raise RuntimeError("this pDMD model is not fitted yet: call fit(snapshots, params) or fit_dataset(ds)")

    # Offline fit ----------------------------------------------------------------------------------
    def fit(
        self,
        snapshots: Any,
        params: ArrayLike,
        *,
        oversample: int = 10,
        power_iterations: int = 2,
        seed: int = 0,
    ) -> "PDMD":
        """Fit the POD basis, the monolithic parametric DMD and the RBF interpolant.

        ``snapshots``: (n_traj, n_t, C, *grid) physical fields, indexable by trajectory;
        ``params``: (n_traj,) parameter values. Returns ``self``; ``fit_info`` reports the POD energy.
        """
        params = np.asarray(params, dtype=np.float64)
        expected = (self.n_fields, *self.grid)
        shape = tuple(snapshots.shape)
        if len(shape) != len(expected) + 2 or shape[2:] != expected:
            raise ValueError(
                f"snapshots must have shape (n_traj, n_t, {', '.join(map(str, expected))}), got {shape}"
            )
        n_traj, n_t = shape[:2]
        if params.shape != (n_traj,):
            raise ValueError(f"params must have shape ({n_traj},) (one per trajectory), got {params.shape}")
        if n_traj < 2 or len(np.unique(params)) != n_traj:
            raise ValueError("pDMD needs at least two trajectories with distinct parameter values")
        if n_t - 1 < self.r:
            raise ValueError(f"the online operator needs n_t - 1 >= r time steps, got n_t = {n_t}, r = {self.r}")
        device = self.stats_mean.device

        def load_block(i: int) -> torch.Tensor:
            x = torch.as_tensor(np.asarray(snapshots[i]), device=device).to(torch.float64)
            return self.normalize(x).reshape(n_t, -1)

        pod = streamed_pod(
            n_traj, load_block, self.r, oversample=oversample, power_iterations=power_iterations, seed=seed
        )
        self.basis = pod["basis"].to(self.stats_mean.dtype)
        self.singular_values = pod["singular_values"].to(torch.float64)
        self.train_coefficients = torch.stack(pod["coefficients"]).to(torch.float64)  # (n_traj, n_t, r)
        self.train_params = torch.as_tensor(params, device=device)
        self.fit_info = {
            "pod_method": "randomized SVD, streamed per trajectory",
            "pod_energy": pod["energy"],
            "pod_passes": pod["passes"],
            "oversample": oversample,
            "power_iterations": power_iterations,
        }
        self._reset_dmd()
        self.parametric_dmd()  # fit the monolithic DMD now, so that its warnings surface at fit time
        self.fit_info["dmd_condition_number"] = self.dmd_condition_number
        return self

    def fit_dataset(self, dataset: Dataset, **kwargs: Any) -> "PDMD":
        """Fit on the train split of a :class:`dks_gym.dataset.Dataset` (read one trajectory at a time)."""
        return self.fit(dataset.fields("train"), dataset.params("train"), **kwargs)

    def _reset_dmd(self) -> None:
        self._pdmd = None
        self._forecast_cache = None
        self._operator_cache.clear()

    def parametric_dmd(self) -> Any:
        """The fitted ``pydmd.ParametricDMD`` (rebuilt from the stored coefficients after loading)."""
        self._require_fitted()
        if self._pdmd is None:
            with one_blas_thread():  # the same fit whatever numpy's thread count (dks_gym.threads)
                self._pdmd = self._fit_parametric_dmd()
        return self._pdmd

    def _fit_parametric_dmd(self) -> Any:
        """PyDMD's monolithic ``ParametricDMD`` with the RBF interpolant, fitted to the stored coefficients."""
        from pydmd import DMD, ParametricDMD

        from .rbf import MultiquadricRBF

        coeffs = np.ascontiguousarray(self.train_coefficients.detach().cpu().numpy().transpose(0, 2, 1))
        pdmd = ParametricDMD(
            DMD(svd_rank=self.r, tikhonov_regularization=self._pydmd_tikhonov(coeffs)),
            _ReducedCoordinates(),
            MultiquadricRBF(smoothing=self.rbf_smoothing),
        )
        # PyDMD warns when the stacked coefficients' condition number exceeds 1e5, which POD coefficients
        # of smooth flows always do; the rank-r truncation and ``dmd_tikhonov`` are what handle it. Keep
        # the number as a diagnostic (``dmd_condition_number``) instead of repeating the warning.
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            # a copy: PyDMD keeps the array, and a view would dangle once torch moves the tensor's storage
            # (share_memory_(), which a process pool's pickler calls)
            pdmd.fit(coeffs, self.train_params.cpu().numpy().copy())
        self.dmd_condition_number = None
        for w in caught:
            found = _CONDITION_WARNING.match(str(w.message))
            if found:
                self.dmd_condition_number = float(found.group(1))
            else:
                warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
        return pdmd

    def _pydmd_tikhonov(self, coeffs: np.ndarray) -> float | None:
        """PyDMD's ``tikhonov_regularization`` for ``dmd_tikhonov``, from coefficients (n_traj, r, n_t).

        PyDMD replaces each singular value s of its X (the stacked coefficients without the last time) by
        (s^2 + t ||X||_F) / s; t = (dmd_tikhonov * s_max)^2 / ||X||_F makes that the Tikhonov filter
        s / (s^2 + lambda^2) with lambda = dmd_tikhonov * s_max, relative to the data's own scale.
        """
        if self.dmd_tikhonov == 0:
            return None
        x = coeffs[:, :, :-1].reshape(-1, coeffs.shape[2] - 1)
        return float((self.dmd_tikhonov * np.linalg.norm(x, 2)) ** 2 / np.linalg.norm(x))

    # Online operator ------------------------------------------------------------------------------
    def interpolated_coefficients(self, mu: ArrayLike) -> np.ndarray:
        """z_k(mu) of Eq. A3 for every training time step, (n_mu, n_t, r) float64 (DMD then RBF in mu)."""
        pdmd = self.parametric_dmd()
        pdmd.parameters = np.atleast_1d(np.asarray(mu, dtype=np.float64))
        with one_blas_thread():  # the RBF's ill-conditioned solve moves with the thread count otherwise
            coeffs = pdmd.interpolated_modal_coefficients  # (n_mu, r, n_t), complex from the DMD modes
        return np.ascontiguousarray(np.real(coeffs).transpose(0, 2, 1))

    def online_operator(self, mu: ArrayLike) -> torch.Tensor:
        """A~(mu) fitted to the interpolated coefficients by Eq. A4, (B, r, r) float64, cached per mu."""
        mu_np = np.atleast_1d(np.asarray(torch.as_tensor(mu).detach().cpu(), dtype=np.float64))
        missing = sorted({float(m) for m in mu_np} - set(self._operator_cache))
        if missing:
            for m, zk in zip(missing, self.interpolated_coefficients(missing)):
                self._operator_cache[m] = self.fit_operator(zk)
        ops = np.stack([self._operator_cache[float(m)] for m in mu_np])
        return torch.as_tensor(ops, device=self.stats_mean.device)

    def differentiable_operator(self, mu: torch.Tensor) -> torch.Tensor:
        """A~(mu) (B, r, r) float64 as a torch function of ``mu`` (B,): the same numbers as
        :meth:`online_operator` (to round-off), differentiable in mu, for a filter that estimates mu.

        The RBF interpolant of Eq. A3 is linear in the values it interpolates, so the interpolated coefficients
        are ``W(mu) @ F``: ``F`` the DMD-forecast coefficients of the training parameters (n_train, n_t, r),
        ``W(mu)`` the interpolant's cardinal weights, [phi(eps |mu - mu_j|), 1] times the inverse of the
        system scipy solves (the multiquadric kernel with its ridge, bordered by the constant). Eq. A4 is then
        the Tikhonov (or pseudoinverse) fit in torch."""
        from .rbf import cardinal_weights

        weights = cardinal_weights(self.train_params.cpu().numpy()[:, None], mu.to(torch.float64),
                                   self.rbf_smoothing)  # (B, n_train)
        z = torch.einsum("bj,jtr->btr", weights, self._forecast_training_coefficients())
        z0, z1 = z[:, :-1].mT, z[:, 1:].mT  # (B, r, n_t - 1)
        if self.pinv_rtol is not None:
            return z1 @ torch.linalg.pinv(z0, rtol=self.pinv_rtol)
        lam2 = (self.operator_tikhonov * torch.linalg.matrix_norm(z0, ord=2)) ** 2
        gram = z0 @ z0.mT + lam2[:, None, None] * torch.eye(self.r, dtype=z.dtype, device=z.device)
        return torch.linalg.solve(gram, z0 @ z1.mT).mT  # Z1 Z0^T (Z0 Z0^T + lambda^2 I)^-1

    def _forecast_training_coefficients(self) -> torch.Tensor:
        """The DMD-forecast coefficients of the training parameters that Eq. A3 interpolates, (n_train, n_t, r)."""
        if self._forecast_cache is None:
            pdmd = self.parametric_dmd()
            with one_blas_thread():
                forecast = pdmd._predict_modal_coefficients()
            forecast = np.real(forecast).reshape(len(self.train_params), self.r, -1)
            self._forecast_cache = torch.as_tensor(np.ascontiguousarray(forecast.transpose(0, 2, 1)))
        return self._forecast_cache.to(self.stats_mean.device)

    def fit_operator(self, coefficients: np.ndarray) -> np.ndarray:
        """Eq. A4 for one coefficient sequence (n_t, r): the A (r, r) with z_{k+1} ~ A z_k, float64.

        By default the Tikhonov solution Z_{1:} Z_{:-1}^T (Z_{:-1} Z_{:-1}^T + lambda^2 I)^{-1}, computed as
        Z_{1:} V diag(s / (s^2 + lambda^2)) U^T from the SVD Z_{:-1} = U diag(s) V^T, with lambda =
        ``operator_tikhonov`` * s_max; with ``pinv_rtol`` set, Z_{1:} Z_{:-1}^+ truncated at that cutoff.
        """
        z = np.asarray(coefficients, dtype=np.float64)
        z0, z1 = z[:-1].T, z[1:].T  # (r, n_t - 1)
        with one_blas_thread():
            if self.pinv_rtol is not None:
                return z1 @ np.linalg.pinv(z0, rcond=self.pinv_rtol)
            u, s, vt = np.linalg.svd(z0, full_matrices=False)
            lam2 = (self.operator_tikhonov * s[0]) ** 2 if s.size else 0.0
            filt = np.divide(s, s * s + lam2, out=np.zeros_like(s), where=s > 0)
            return (z1 @ vt.T * filt) @ u.T

    # Interface ------------------------------------------------------------------------------------
    def encode(self, x: ArrayLike, mu: ArrayLike | None = None) -> torch.Tensor:
        """POD coefficients U_r^T normalize(x), (B, r), computed in float64 and returned in x's dtype; mu is
        not used. (A float32 product over the sphere's 10^6 values moved the final error of a forward run by
        5e-3 relative against float64.)"""
        self._require_fitted()
        x = self._fields(x)
        return (self.normalize(x.double()).flatten(1) @ self.basis.double()).to(x.dtype)

    def decode(self, z: ArrayLike, mu: ArrayLike | None = None) -> torch.Tensor:
        """denormalize(U_r z), (B, C, *grid); mu is not used."""
        self._require_fitted()
        z = self._latent(z)
        x = z @ self.basis.to(z.dtype).T
        return self.denormalize(x.view(z.shape[0], self.n_fields, *self.grid))

    def forecast(self, z: ArrayLike, mu: ArrayLike) -> torch.Tensor:
        """A~(mu) z, computed in float64 and returned in z's dtype.

        In float32 the product's own round-off, compounded over a forward run, changed the final error of
        a 99-step Burgers run by up to 1e-3 relative between thread counts; rounding only the result keeps
        float32 runs within 1e-4 of float64 ones."""
        z = self._latent(z)
        mu = self._param(mu, z.shape[0])
        # differentiated in mu (a filter estimating it): the torch operator; else the cached PyDMD one
        a = self.differentiable_operator(mu) if mu.requires_grad else self.online_operator(mu)
        return (a @ z.to(a.dtype)[..., None])[..., 0].to(z.dtype)

    def forecast_jacobian(self, z: ArrayLike, mu: ArrayLike) -> torch.Tensor:
        z = self._latent(z)
        return self.online_operator(self._param(mu, z.shape[0])).to(z.dtype)

    def filter_forecast_jacobian(self, mu: torch.Tensor) -> torch.Tensor:
        """A~(mu) for the whole episode (the map is linear), computed once."""
        with torch.no_grad():
            return self.online_operator(mu).to(mu)

    def filter_observe_jacobian(self, mu: torch.Tensor, sensor_rows: Callable[[int], np.ndarray],
                                channel: str) -> Callable:
        """h is affine, so its Jacobian S diag(std) U_r at the current sensors is exact, (n, m, r)."""

        def jacobian(z: torch.Tensor) -> torch.Tensor:
            return torch.stack([self.observation_matrix(s, channel) for s in sensor_rows(z.shape[0])]).to(z)

        return jacobian

    def decoder_jacobian(self, z: torch.Tensor, mu: torch.Tensor | None = None) -> torch.Tensor:
        """The decoder is affine: diag(std) U_r for every state, (B, C, n_cells, r) (a broadcast view)."""
        self._require_fitted()
        n_cells = math.prod(self.grid)
        G = self.basis.to(z).view(self.n_fields, n_cells, -1) * self.stats_std.to(z)[:, None, None]
        return G.expand(z.shape[0], *G.shape)

    def decoder_variance(self, z: torch.Tensor, mu: torch.Tensor | None, factor: torch.Tensor) -> torch.Tensor:
        """``diag(G F F^T G^T)`` with the exact, constant ``G = diag(std) U_r``: ``std^2 |U_r F|^2`` per cell,
        (B, C, *grid); one matrix product ``U_r [F_1 ... F_B]`` in chunks of cells."""
        self._require_fitted()
        batch, r, d = factor.shape
        basis = self.basis.to(factor.dtype)
        columns = factor.permute(1, 0, 2).reshape(r, batch * d)
        var = torch.empty(basis.shape[0], batch, dtype=factor.dtype, device=factor.device)
        step = max(1, _CHUNK_NUMBERS // (batch * d))
        for s in range(0, basis.shape[0], step):
            var[s:s + step] = (basis[s:s + step] @ columns).view(-1, batch, d).pow(2).sum(-1)
        var = var.T.reshape(batch, self.n_fields, *self.grid)
        return var * self._channel_view(self.stats_std, var.dtype).pow(2)

    def checkpoint_metadata(self) -> dict[str, Any]:
        """The regularization settings (also in the state dict, which is what loading uses) and the fit's
        diagnostics."""
        return {"pdmd": {**self.settings, "fit_info": self.fit_info}}

    def observation_matrix(self, sensors: ArrayLike, channel: int | str) -> torch.Tensor:
        """J = S diag(std) U_r restricted to ``channel`` at ``sensors``, (m, r): h(z) = J z + mean[channel]."""
        self._require_fitted()
        return self._observation_rows(self._sensor_index(sensors), self._channel_index(channel))

    def _observation_rows(self, idx: torch.Tensor, c: int) -> torch.Tensor:
        """The rows of diag(std) U_r of channel ``c`` at cells ``idx`` (any shape) -> (*idx.shape, r)."""
        return self.basis[c * math.prod(self.grid) + idx] * self.stats_std[c]

    def observe(self, z: ArrayLike, mu: ArrayLike, sensors: ArrayLike, channel: int | str) -> torch.Tensor:
        """h(z) = S U_r z de-normalized, without forming the full field, (B, m); ``sensors`` one layout (m,) or
        one per row (B, m) (rows of the basis per row where the layouts differ)."""
        self._require_fitted()
        z = self._latent(z)
        idx = self._sensor_index(sensors, z.shape[0])
        if idx.ndim == 2 and bool((idx == idx[:1]).all()):
            idx = idx[0]
        c = self._channel_index(channel)
        J = self._observation_rows(idx, c)  # (m, r) or (B, m, r)
        y = z @ J.to(z.dtype).T if idx.ndim == 1 else (J.to(z.dtype) @ z[:, :, None])[..., 0]
        return y + self.stats_mean[c].to(z.dtype)

    # Persistence ----------------------------------------------------------------------------------
    def get_extra_state(self) -> torch.Tensor:
        """The regularization settings as a float64 tensor (NaN: ``pinv_rtol`` None), saved in the state dict.

        Extra state rather than a buffer, so that ``.to(dtype)`` never rounds it."""
        return torch.tensor([math.nan if v is None else v for v in self.settings.values()], dtype=torch.float64)

    def set_extra_state(self, state: Any) -> None:
        values = torch.as_tensor(state, dtype=torch.float64).tolist()
        if len(values) != len(self._SETTINGS):
            raise ValueError(f"pDMD extra state must hold {len(self._SETTINGS)} settings, got {len(values)}")
        for name, value in zip(self._SETTINGS, values):
            setattr(self, name, None if math.isnan(value) else value)

    def _load_from_state_dict(self, state_dict: dict, prefix: str, *args: Any, **kwargs: Any) -> None:
        for name in self._RESIZABLE:  # sizes are known only after a fit
            key = prefix + name
            if key in state_dict:
                setattr(self, name, torch.empty_like(state_dict[key], device=getattr(self, name).device))
        # A state dict saved before the settings were stored keeps this model's settings (the defaults).
        state_dict.setdefault(prefix + "_extra_state", self.get_extra_state())
        self._reset_dmd()
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    def _apply(self, fn: Any, *args: Any, **kwargs: Any) -> "PDMD":
        self._operator_cache.clear()
        return super()._apply(fn, *args, **kwargs)
