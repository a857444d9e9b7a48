"""The uniform latent-model interface the filters use, and the encoder-decoder models around a learned latent map.

Every model is a ``torch.nn.Module`` with attributes ``benchmark``, ``kind`` ("koopman", "mlp", "xlstm",
"pdmd"), ``r``, ``dt``, ``grid`` and the methods (all batched over a leading dimension B)::

    encode(x, mu)            x (B, C, *grid) physical, mu (B,)  -> z (B, r)
    decode(z, mu)            z (B, r)                           -> x (B, C, *grid) physical
    forecast(z, mu)          z_k (B, r)                         -> z_{k+1} (B, r)        (Eq. 5)
    forecast_jacobian(z, mu)                                    -> dF/dz (B, r, r)
    observe(z, mu, sensors, channel)    sensors (m,) or (B, m)  -> S(decode(z)) (B, m)   (Eq. 12)
    rollout(z0, mu, n_steps)                                    -> (B, n_steps + 1, r)
    filter_forecast_jacobian(mu)            dF/dz as the filters take it: a constant (B, r, r) or a callable
    filter_observe_jacobian(mu, rows, channel)  dh/dz as the filters take it: None (autodiff) or a callable
    decoder_jacobian(z, mu)                                     -> d decode/dz (B, C, n_cells, r)
    decoder_variance(z, mu, factor)         diag(G F F^T G^T), G = d decode/dz (B, C, *grid), or None
    decode_with_variance(z, mu, factor)     (decode(z, mu), decoder_variance(z, mu, factor)), one pass (neural)

A model owns its linearization: the Koopman model hands the filters K(mu) (cached per mu), pDMD A~(mu)
and its exact observation and decoder matrices, the MLP and xLSTM maps an autodiff Jacobian.

Fields enter and leave in physical units: each model holds the per-channel train-split mean and std as
buffers and normalizes inside ``encode`` and de-normalizes inside ``decode``. Where the benchmark has a
cell type, the encoder appends it (a buffer, raw integer codes as float) as an extra input channel; the
sphere decoder also outputs a cell-type channel (the paper's 5 output channels), which ``decode`` drops
and :meth:`NeuralLatentModel.reconstruction_target` keeps, so a training loss on
``decode_normalized`` includes it.
"""

from __future__ import annotations

from collections import OrderedDict
from typing import Any, Callable

import numpy as np
import torch
from torch import nn

from .backbones import ConvDecoder, ConvEncoder, ParametricEncoder, quiet_forward_ad
from .decoder_variance import decoder_variance, supports_decoder_variance
from .embedding import ParameterEmbedding
from .presets import EMBEDDING_HIDDEN_LAYERS, BenchmarkShape, backbone_spec

ArrayLike = Any  # torch.Tensor, np.ndarray, float or sequence of floats
Map = Callable[[torch.Tensor], torch.Tensor]


def count_parameters(module: nn.Module) -> int:
    """Number of parameters of ``module`` (trainable or not)."""
    return sum(p.numel() for p in module.parameters())


class LatentModel(nn.Module):
    """Base class: benchmark geometry, normalization buffers, input checks and the shared helpers."""

    kind: str = ""
    #: True for models fitted in closed form (pDMD): no training schedule, preset or window length T.
    fitted_in_closed_form: bool = False

    def __init__(
        self,
        shape: BenchmarkShape,
        r: int,
        *,
        dt: float | None = None,
        stats_mean: ArrayLike | None = None,
        stats_std: ArrayLike | None = None,
    ) -> None:
        super().__init__()
        # Measured on held-out trajectories after training (models.calibration.calibrate): "Q", the latent
        # one-step residual covariance (r, r), and "reconstruction_variance", per cell (C, *grid).
        self.calibration: dict[str, torch.Tensor] = {}
        if int(r) != r or r < 1:
            raise ValueError(f"latent dimension r must be a positive integer, got {r!r}")
        self.shape = shape
        self.benchmark = shape.name
        self.r = int(r)
        self.dt = float(shape.dt if dt is None else dt)
        if not self.dt > 0:
            raise ValueError(f"dt must be positive, got {self.dt}")
        self.grid = shape.grid
        self.n_fields = shape.n_fields
        c = shape.n_fields
        mean = torch.zeros(c) if stats_mean is None else self._stats_tensor(stats_mean, "stats_mean")
        std = torch.ones(c) if stats_std is None else self._stats_tensor(stats_std, "stats_std")
        if stats_std is not None and not bool((std > 0).all()):
            raise ValueError(f"stats_std must be positive for every channel, got {std.tolist()}")
        self.register_buffer("stats_mean", mean)
        self.register_buffer("stats_std", std)

    def _stats_tensor(self, values: ArrayLike, name: str) -> torch.Tensor:
        t = torch.as_tensor(np.asarray(values, dtype=np.float32))
        if t.shape != (self.n_fields,):
            raise ValueError(
                f"{name} must have one value per channel of {self.benchmark} ({self.n_fields}), got shape "
                f"{tuple(t.shape)}; pass the dataset's ds.stats_mean / ds.stats_std"
            )
        return t.to(torch.get_default_device())

    # Checks ---------------------------------------------------------------------------------------
    def _fields(self, x: ArrayLike) -> torch.Tensor:
        x = torch.as_tensor(x, device=self.stats_mean.device)
        if not x.is_floating_point():
            x = x.to(self.stats_mean.dtype)
        expected = (self.n_fields, *self.grid)
        if x.ndim != len(expected) + 1 or tuple(x.shape[1:]) != expected:
            raise ValueError(
                f"{self.benchmark} fields must have shape (B, {', '.join(map(str, expected))}) in physical "
                f"units, got {tuple(x.shape)}; add a leading batch axis with x[None] for a single frame"
            )
        return x

    def _latent(self, z: ArrayLike) -> torch.Tensor:
        z = torch.as_tensor(z, device=self.stats_mean.device)
        if z.ndim != 2 or z.shape[1] != self.r:
            raise ValueError(f"latent states must have shape (B, {self.r}), got {tuple(z.shape)}")
        return z

    def _param(self, mu: ArrayLike, batch: int) -> torch.Tensor:
        mu = torch.as_tensor(mu, device=self.stats_mean.device)
        if not mu.is_floating_point():
            mu = mu.to(torch.float64)
        if mu.ndim == 0:
            mu = mu.expand(batch)
        if mu.shape != (batch,):
            raise ValueError(f"mu must be a scalar or have shape ({batch},) to match the batch, got {tuple(mu.shape)}")
        return mu

    # Normalization --------------------------------------------------------------------------------
    def _channel_view(self, t: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
        return t.to(dtype).view(-1, *([1] * len(self.grid)))

    def normalize(self, x: torch.Tensor) -> torch.Tensor:
        """Physical fields (B, C, *grid) -> per-channel standardized fields."""
        return (x - self._channel_view(self.stats_mean, x.dtype)) / self._channel_view(self.stats_std, x.dtype)

    def denormalize(self, x: torch.Tensor) -> torch.Tensor:
        """Standardized fields (B, C, *grid) -> physical units."""
        return x * self._channel_view(self.stats_std, x.dtype) + self._channel_view(self.stats_mean, x.dtype)

    # Interface ------------------------------------------------------------------------------------
    def encode(self, x: ArrayLike, mu: ArrayLike) -> torch.Tensor:
        """Physical fields (B, C, *grid) -> latent states (B, r)."""
        raise NotImplementedError

    def decode(self, z: ArrayLike, mu: ArrayLike) -> torch.Tensor:
        """Latent states (B, r) -> physical fields (B, C, *grid)."""
        raise NotImplementedError

    def forecast(self, z: ArrayLike, mu: ArrayLike) -> torch.Tensor:
        """One latent step z_{k+1} = F(z_k, mu) (Eq. 5), (B, r) -> (B, r)."""
        raise NotImplementedError

    def forecast_jacobian(self, z: ArrayLike, mu: ArrayLike) -> torch.Tensor:
        """dF/dz at z, (B, r, r)."""
        raise NotImplementedError

    def rollout(self, z0: ArrayLike, mu: ArrayLike, n_steps: int) -> torch.Tensor:
        """Open-loop latent trajectory (B, n_steps + 1, r) starting at z0 (the forward run)."""
        z = self._latent(z0)
        mu = self._param(mu, z.shape[0])
        states = [z]
        for _ in range(int(n_steps)):
            states.append(self.forecast(states[-1], mu))
        return torch.stack(states, dim=1)

    # How the filters linearize this model ---------------------------------------------------------
    def filter_forecast_jacobian(self, mu: torch.Tensor) -> torch.Tensor | Map:
        """dF/dz with ``mu`` (B,) bound, as :class:`~dks_gym.filters.LatentDynamics` takes it.

        Default: a callable over ``k * B`` stacked rows (row j belongs to element j // k) that evaluates
        :meth:`forecast_jacobian` at the filter's state. Linear maps return their constant (B, r, r) operator.
        """
        batch = mu.shape[0]
        return lambda z: self.forecast_jacobian(z, mu.repeat_interleave(z.shape[0] // batch, dim=0))

    def filter_observe_jacobian(self, mu: torch.Tensor, sensor_rows: Callable[[int], np.ndarray],
                                channel: str) -> Map | None:
        """dh/dz of h(z) = S(decode(z)) with ``mu`` (B,) bound, for the filters: None means autodiff through the
        decoder.

        ``sensor_rows(n)`` gives the (n, m) sensor indices of n stacked rows at the current step (row j belongs
        to element j // (n // B)). Models with a linear decoder return a callable giving the exact (n, m, r)
        Jacobian; the neural models one giving h(z) and the Jacobian together from only the cells the sensors
        depend on, where that saves work (see :class:`~dks_gym.filters.LatentDynamics`).
        """
        return None

    def decoder_jacobian(self, z: torch.Tensor, mu: torch.Tensor) -> torch.Tensor:
        """d decode(z, mu) / dz at each latent state, detached, (B, C, n_cells, r) in physical units.

        Forward-mode autodiff, one Jacobian-vector product per latent direction (r decoder passes); the
        caller chunks B to bound memory (B * C * n_cells * r numbers). Linear decoders override it.
        """

        def decode(x: torch.Tensor) -> torch.Tensor:
            return self.decode(x, mu).flatten(2)

        cols = []
        with quiet_forward_ad():
            for i in range(z.shape[1]):
                tangent = torch.zeros_like(z)
                tangent[:, i] = 1.0
                cols.append(torch.func.jvp(decode, (z,), (tangent,))[1].detach())
        return torch.stack(cols, dim=-1)

    def decoder_variance(self, z: torch.Tensor, mu: torch.Tensor, factor: torch.Tensor) -> torch.Tensor | None:
        """``diag(G F F^T G^T)`` with ``G = d decode(z, mu) / dz`` at each latent state and ``factor`` ``F``
        (B, r, d) (``F F^T`` a latent covariance): the decoded variance per cell, (B, C, *grid) in physical
        units squared, a new tensor (the caller may change it in place). None (here) where the model has no
        exact rule of its own: the caller then differentiates ``decode``
        (:func:`~dks_gym.assimilation.jacobian_variance`)."""
        return None

    def observe(self, z: ArrayLike, mu: ArrayLike, sensors: ArrayLike, channel: int | str) -> torch.Tensor:
        """h(z) = S(decode(z)): the decoded ``channel`` (index or name) at flat C-order grid ``sensors``, one layout
        (m,) for every row or one per row (B, m), -> (B, m)."""
        z = self._latent(z)
        idx = self._sensor_index(sensors, z.shape[0])
        fields = self.decode(z, mu).flatten(2)[:, self._channel_index(channel)]
        return fields[:, idx] if idx.ndim == 1 else fields.gather(1, idx)

    def _sensor_index(self, sensors: ArrayLike, batch: int | None = None) -> torch.Tensor:
        """``sensors`` as a long tensor, checked: one layout (m,), or one per row (batch, m) where ``batch`` is
        given."""
        idx = torch.as_tensor(np.asarray(sensors), dtype=torch.long, device=self.stats_mean.device)
        n_cells = int(np.prod(self.grid))
        rows = idx.ndim == 2 and batch is not None and idx.shape[0] == batch
        if not (idx.ndim == 1 or rows) or idx.numel() == 0 or int(idx.min()) < 0 or int(idx.max()) >= n_cells:
            per_row = f", or one such layout per row ({batch}, m)" if batch is not None else ""
            raise ValueError(
                f"sensors must be a non-empty 1D array of flat C-order grid indices in [0, {n_cells}){per_row}, "
                f"got {np.asarray(sensors)!r}"
            )
        return idx

    def _channel_index(self, channel: int | str) -> int:
        if isinstance(channel, str):
            if channel not in self.shape.channels:
                raise ValueError(f"unknown channel {channel!r}; {self.benchmark} has {', '.join(self.shape.channels)}")
            return self.shape.channels.index(channel)
        if not 0 <= int(channel) < self.n_fields:
            raise ValueError(f"channel must be in [0, {self.n_fields}), got {channel}")
        return int(channel)

    def checkpoint_metadata(self) -> dict[str, Any]:
        """Model-specific entries for the checkpoint's metadata (none by default)."""
        return {}

    def extra_repr(self) -> str:
        return f"benchmark={self.benchmark!r}, kind={self.kind!r}, r={self.r}, dt={self.dt}"


class NeuralLatentModel(LatentModel):
    """Encoder E_phi + embedding e_omega, decoder G_psi and a learned latent map F(z, s) (MLP or xLSTM).

    ``latent_map(r, dt)`` builds the map, a module with ``forward(z, s) -> z_next`` for (B, r) states and
    embeddings; it is called after the encoder and decoder exist, so weights drawn from one seed do not
    depend on the map. The forecast Jacobian is autodiff through the map. Parameter counts
    (``param_counts``) follow the paper's table: the encoder includes the embedding, the decoder has no
    parameter of its own for the conditioning (it receives z + s), and the latent map excludes the embedding.
    """

    def __init__(
        self,
        shape: BenchmarkShape,
        kind: str,
        latent_map: Callable[[int, float], nn.Module],
        r: int = 32,
        preset: str = "paper",
        *,
        dt: float | None = None,
        stats_mean: ArrayLike | None = None,
        stats_std: ArrayLike | None = None,
        cell_type: ArrayLike | None = None,
    ) -> None:
        super().__init__(shape, r, dt=dt, stats_mean=stats_mean, stats_std=stats_std)
        self.kind = kind
        self.preset = preset
        spec = backbone_spec(shape, preset)
        embedding = ParameterEmbedding(self.r, shape.param_range, EMBEDDING_HIDDEN_LAYERS)
        self.encoder = ParametricEncoder(ConvEncoder(shape, spec, self.r), embedding)
        self.decoder = ConvDecoder(shape, spec, self.r)
        self.latent_map: nn.Module = latent_map(self.r, self.dt)
        if shape.has_cell_type:
            ct = None if cell_type is None else self._cell_type_tensor(cell_type)
            self.register_buffer("cell_type", ct)
        else:
            if cell_type is not None:
                raise ValueError(f"{shape.name} has no cell type; do not pass cell_type")
            self.cell_type = None

    def _cell_type_tensor(self, cell_type: ArrayLike) -> torch.Tensor:
        ct = torch.tensor(np.asarray(cell_type), dtype=torch.float32)  # a copy: the caller's array may be read-only
        if tuple(ct.shape) != self.grid:
            raise ValueError(f"cell_type must have the grid shape {self.grid}, got {tuple(ct.shape)}")
        return ct.to(torch.get_default_device())

    @property
    def _dtype(self) -> torch.dtype:
        return self.stats_mean.dtype  # the model's floating dtype; inputs of other dtypes are cast to it

    def param_counts(self) -> dict[str, int]:
        """Parameters of the encoder (incl. e(mu)), decoder and latent map, as in the paper's table."""
        return {
            "encoder": count_parameters(self.encoder),
            "decoder": count_parameters(self.decoder),
            "latent_map": count_parameters(self.latent_map),
        }

    # Embedding and normalization ------------------------------------------------------------------
    def embed_param(self, mu: ArrayLike) -> torch.Tensor:
        """s = e_omega(mu), (B,) -> (B, r) (Eq. 6)."""
        mu = torch.as_tensor(mu, device=self.stats_mean.device)
        if mu.ndim != 1:
            raise ValueError(f"mu must have shape (B,), got {tuple(mu.shape)}")
        return self.encoder.embedding(mu)

    def encoder_input(self, x: ArrayLike) -> torch.Tensor:
        """Normalized fields with the cell type appended as the last channel (B, C_in, *grid)."""
        x = self.normalize(self._fields(x))
        return self._with_cell_type(x) if self.shape.has_cell_type else x

    def reconstruction_target(self, x: ArrayLike) -> torch.Tensor:
        """What ``decode_normalized`` should reproduce: normalized fields, plus the cell type on the sphere."""
        x = self.normalize(self._fields(x))
        return self._with_cell_type(x) if self.shape.reconstructs_cell_type else x

    def _with_cell_type(self, x: torch.Tensor) -> torch.Tensor:
        if self.cell_type is None:
            raise RuntimeError(
                f"the {self.benchmark} model needs the cell type as a channel; build it with "
                "cell_type=ds.cell_type (or dataset=ds)"
            )
        ct = self.cell_type.to(x.dtype).expand(x.shape[0], 1, *self.grid)
        return torch.cat([x, ct], dim=1)

    # Interface ------------------------------------------------------------------------------------
    def filter_observe_jacobian(self, mu: torch.Tensor, sensor_rows: Callable[[int], np.ndarray],
                                channel: str) -> Map | None:
        """h(z) and its Jacobian from each sensor's window of the bottleneck (:meth:`ConvDecoder.sensor_jacobian`:
        5 of 128 cells on Burgers, 3 x 3 x 3 of 4 x 4 x 4 on the sphere), a callable ``z -> (h, J)``; None
        (autodiff through the full decoder) where the window is most of the bottleneck (the 2D grids)."""
        if self.decoder.window() is None:
            return None
        c = self._channel_index(channel)
        with torch.no_grad():
            s = self.embed_param(self._param(mu, mu.shape[0]))
        batch = mu.shape[0]

        def jacobian(z: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
            """h(z) and dh/dz at the current sensors, both from the sensors' windows."""
            cells = torch.as_tensor(sensor_rows(z.shape[0]), device=z.device)
            x = z.to(self._dtype) + s.repeat_interleave(z.shape[0] // batch, dim=0)
            values, jac = self.decoder.sensor_jacobian(x, cells, c)
            std, mean = self.stats_std[c].to(jac.dtype), self.stats_mean[c].to(jac.dtype)
            return (values * std + mean).to(z.dtype), (jac * std).to(z.dtype)  # decode() de-normalizes: x std + mean

        return jacobian

    def observe(self, z: ArrayLike, mu: ArrayLike, sensors: ArrayLike, channel: int | str) -> torch.Tensor:
        """h(z) (see :meth:`LatentModel.observe`), decoded from only the cells the sensors read
        (:meth:`ConvDecoder.at_cells`) where the decoder's receptive field is a small part of the bottleneck (the
        Burgers and sphere grids; the 2D grids decode the whole field): the same numbers to float round-off."""
        if self.decoder.window() is None:
            return super().observe(z, mu, sensors, channel)
        z = self._latent(z)
        idx = self._sensor_index(sensors, z.shape[0])
        c = self._channel_index(channel)
        values = self.decoder.at_cells(self._decoder_input(z, mu), idx.expand(z.shape[0], -1), c).to(z.dtype)
        return values * self.stats_std[c].to(z.dtype) + self.stats_mean[c].to(z.dtype)  # as decode() de-normalizes

    def decoder_variance(self, z: torch.Tensor, mu: torch.Tensor, factor: torch.Tensor,
                         preactivations: list[torch.Tensor] | None = None) -> torch.Tensor | None:
        """``diag(G F F^T G^T)`` per cell, (B, C, *grid) physical units: the decoder linearized by hand, stage by
        stage (:func:`~dks_gym.models.decoder_variance.decoder_variance`: exact, the cost of a few decodes
        rather than ``d`` Jacobian-vector products); None for a decoder it cannot linearize.
        ``preactivations``: what :meth:`decode_normalized` recorded at this ``z`` (skips a primal pass)."""
        if not supports_decoder_variance(self.decoder):
            return None
        z = self._latent(z)
        var = decoder_variance(self.decoder, self._decoder_input(z, mu), factor.to(self._dtype),
                               preactivations)[:, : self.n_fields]
        return var.mul_(self._channel_view(self.stats_std, var.dtype).pow(2)).to(z.dtype)

    def decode_with_variance(self, z: torch.Tensor, mu: torch.Tensor,
                             factor: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
        """:meth:`decode` (bitwise) and :meth:`decoder_variance` at the same ``z`` from one forward pass of the
        decoder: its GELU inputs are the slopes' arguments."""
        if not supports_decoder_variance(self.decoder):
            return self.decode(z, mu), None
        preactivations: list[torch.Tensor] = []
        field = self.denormalize(self.decode_normalized(z, mu, preactivations)[:, : self.n_fields])  # as decode()
        return field, self.decoder_variance(z, mu, factor, preactivations)

    def encode(self, x: ArrayLike, mu: ArrayLike) -> torch.Tensor:
        """z = E_phi(x, mu) + e_omega(mu) from physical fields (B, C, *grid)."""
        xin = self.encoder_input(x)
        z = self.encoder(xin.to(self._dtype), self._param(mu, xin.shape[0]))
        return z.to(xin.dtype)

    def decode_normalized(self, z: ArrayLike, mu: ArrayLike,
                          preactivations: list[torch.Tensor] | None = None) -> torch.Tensor:
        """G_psi(z + s): all decoder output channels (B, C_out, *grid), normalized units (``preactivations``:
        see :meth:`ConvDecoder.forward`)."""
        z = self._latent(z)
        return self.decoder(self._decoder_input(z, mu), preactivations).to(z.dtype)

    def _decoder_input(self, z: torch.Tensor, mu: ArrayLike) -> torch.Tensor:
        """z + s, s = e(mu): what the decoder reads (in its dtype)."""
        return z.to(self._dtype) + self.embed_param(self._param(mu, z.shape[0]))

    def decode(self, z: ArrayLike, mu: ArrayLike) -> torch.Tensor:
        """Physical fields (B, C, *grid); the sphere's cell-type output channel is dropped."""
        return self.denormalize(self.decode_normalized(z, mu)[:, : self.n_fields])

    def forecast(self, z: ArrayLike, mu: ArrayLike) -> torch.Tensor:
        """z_{k+1} = F(z_k, e(mu)) through the learned map (Eq. 5)."""
        z = self._latent(z)
        mu = self._param(mu, z.shape[0])
        return self.latent_map(z.to(self._dtype), self.embed_param(mu)).to(z.dtype)

    def forecast_jacobian(self, z: ArrayLike, mu: ArrayLike) -> torch.Tensor:
        """Autodiff Jacobian of the map at z (torch.func), (B, r, r)."""
        z = self._latent(z)
        mu = self._param(mu, z.shape[0])
        s = self.embed_param(mu)

        def one_step(z1: torch.Tensor, s1: torch.Tensor) -> torch.Tensor:
            return self.latent_map(z1[None], s1[None])[0]

        return torch.func.vmap(torch.func.jacrev(one_step))(z.to(self._dtype), s).to(z.dtype)


class KoopmanModel(NeuralLatentModel):
    """The deep Koopman model: a linear latent map z_{k+1} = K(mu; dt) z_k (Eqs. 7-9), K cached per mu."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._operator_cache: OrderedDict[tuple, torch.Tensor] = OrderedDict()

    def forecast(self, z: ArrayLike, mu: ArrayLike) -> torch.Tensor:
        z = self._latent(z)
        mu = self._param(mu, z.shape[0])
        return (self.koopman_operator(mu).to(z.dtype) @ z[..., None])[..., 0]  # Eq. 7

    def forecast_jacobian(self, z: ArrayLike, mu: ArrayLike) -> torch.Tensor:
        """K(mu; dt), whatever z (the map is linear)."""
        z = self._latent(z)
        return self.koopman_operator(self._param(mu, z.shape[0])).to(z.dtype)

    def filter_forecast_jacobian(self, mu: torch.Tensor) -> torch.Tensor:
        """K(mu) for the whole episode, computed once."""
        with torch.no_grad():
            return self.koopman_operator(mu).to(mu.dtype)

    def koopman_operator(self, mu: ArrayLike) -> torch.Tensor:
        """K(mu; dt) (B, r, r) (Eq. 7); cached per mu when no gradient is being recorded."""
        mu = torch.as_tensor(mu, device=self.stats_mean.device)
        mu = self._param(mu, mu.shape[0] if mu.ndim else 1)
        if mu.requires_grad:  # differentiated in mu (a filter estimating it): every row, no cache
            return self.latent_map.operator(self.encoder.embedding(mu))
        if torch.is_grad_enabled() and any(p.requires_grad for p in self._operator_parameters()):
            return self._compute_operator(mu)
        # In-place updates (optimizer steps, load_state_dict) bump the parameter versions.
        versions = tuple(p._version for p in self._operator_parameters())
        # The training mode is part of the key: the latent map computes K in another formulation there.
        key = (str(mu.device), str(mu.dtype), mu.detach().cpu().numpy().tobytes(), versions, self.training)
        if key in self._operator_cache:
            self._operator_cache.move_to_end(key)
            return self._operator_cache[key]
        with torch.no_grad():
            k = self._compute_operator(mu)
        self._operator_cache[key] = k
        while len(self._operator_cache) > 16:
            self._operator_cache.popitem(last=False)
        return k

    def _operator_parameters(self) -> list[nn.Parameter]:
        return [*self.encoder.embedding.parameters(), *self.latent_map.parameters()]

    def _compute_operator(self, mu: torch.Tensor) -> torch.Tensor:
        values, inverse = torch.unique(mu, return_inverse=True)
        return self.latent_map.operator(self.encoder.embedding(values))[inverse]

    def _apply(self, fn: Any, *args: Any, **kwargs: Any) -> "KoopmanModel":
        self._operator_cache.clear()  # device or dtype moves invalidate cached operators
        return super()._apply(fn, *args, **kwargs)

