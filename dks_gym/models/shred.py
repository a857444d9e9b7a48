"""SHRED, the shallow recurrent decoder (Williams, Zahn & Kutz, Proc. R. Soc. A 480, 2024): a non-Bayesian baseline.

It maps the recent history of a fixed layout's readings straight to the field, with no latent dynamics and no
filter; the placement benchmark scores it beside the latent filters on the same episodes, so that users see
where a filter with a physics-shaped latent model wins and where a pure sequence model does. It is not one of
the latent models (:data:`~dks_gym.names.MODEL_KINDS`): it has no forecast and no Jacobian.

A torch implementation of the published architecture, not the ``pyshred`` package: installing pyshred 1.1.0
beside dks-gym would downgrade numpy to 1.26.4 (dks-gym runs on numpy 2) and pull pysindy, pandas, cmake and
scs (``pip install --dry-run pyshred``). As published: an LSTM of 2 layers of 64 units over the last ``lags``
frames of readings, whose last hidden state goes through a shallow decoder of 350 and 400 ReLU units with
dropout 0.1. As in
pyshred's compressed mode (and SHRED-ROM), the decoder outputs the leading ``rank`` POD coefficients of the
standardized training fields, so the output layer does not scale with the grid; :meth:`Shred.project`
gives the projection whose error bounds it.

Inputs per frame: the m readings standardized per sensor (0 where missing), the m presence flags, the
standardized parameter mu and the time since the episode began: the information the filters have (they know
mu, start from frame 0 and step once per frame, and skip frame 0's reading), so
the estimate at frame k uses the readings of frames max(1, k - lags + 1)..k, zero-padded before frame 1.
Training on the training split, read through :class:`~dks_gym.envs.SensingEnv` with the test episodes'
noise level and faults and ``noise_seeds`` noise realizations per trajectory: Adam (1e-3), batches of 64,
MSE of the POD coefficients, early stopping (patience 20 epochs) on a held-out tenth of the training
trajectories, keeping the best epoch. Reproducible from ``seed``.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass
from typing import Any, Sequence

import numpy as np
import torch
from torch import nn

from ..dataset import Dataset
from ..envs import SensingEnv, SensorFaults
from ..threads import torch_threads


@dataclass(frozen=True)
class ShredConfig:
    """SHRED's settings; the defaults are the published architecture (see the module docstring)."""

    lags: int = 32
    hidden: int = 64
    layers: int = 2
    decoder: tuple[int, int] = (350, 400)
    dropout: float = 0.1
    rank: int = 64
    epochs: int = 300
    patience: int = 20
    batch_size: int = 64
    lr: float = 1e-3
    noise_seeds: int = 2
    seed: int = 0


class ShredNetwork(nn.Module):
    """LSTM over the reading history, then the shallow decoder to the POD coefficients."""

    def __init__(self, n_inputs: int, n_outputs: int, config: ShredConfig) -> None:
        super().__init__()
        self.lstm = nn.LSTM(n_inputs, config.hidden, config.layers, batch_first=True)
        widths = (config.hidden, *config.decoder)
        layers: list[nn.Module] = []
        for a, b in zip(widths[:-1], widths[1:]):
            layers += [nn.Linear(a, b), nn.ReLU(), nn.Dropout(config.dropout)]
        self.decoder = nn.Sequential(*layers, nn.Linear(widths[-1], n_outputs))

    def forward(self, history: torch.Tensor) -> torch.Tensor:
        """(B, lags, n_inputs) -> (B, rank)."""
        _, (h, _) = self.lstm(history)
        return self.decoder(h[-1])


def read_episodes(dataset: Dataset, layout: np.ndarray, trajectories: Sequence[int], noise_seeds: Sequence[int], *,
                  split: str, noise_level: float, faults: SensorFaults | dict[str, Any] | None) -> np.ndarray:
    """The readings of ``layout`` over every (trajectory, noise seed) episode, (E, n_t, m) float32 (NaN where
    missing), as a SensingEnv serves them: the filters' episodes read the same values."""
    layout = np.asarray(layout, dtype=np.int64)
    env = SensingEnv(dataset.benchmark, preset=dataset.preset or "paper", data_path=str(dataset.path), split=split,
                     noise_level=noise_level, n_sensors=len(layout), sensors=layout, faults=faults)
    out = np.empty((len(trajectories), dataset.n_frames, len(layout)), dtype=np.float32)
    for e, (t, s) in enumerate(zip(trajectories, noise_seeds)):
        out[e, 0] = env.reset(options={"trajectory": int(t), "noise_seed": int(s)})[0]
        for k in range(1, dataset.n_frames):
            out[e, k] = env.step(None)[0]
    env.close()
    return out


class Shred:
    """A SHRED reconstructor for one layout: :meth:`fit` on the training split, :meth:`reconstruct` episodes.

    ``faults`` and ``noise_level``: those of the episodes it will see (it is trained on them).
    """

    def __init__(self, dataset: Dataset, layout: np.ndarray, *, noise_level: float = 0.2,
                 faults: SensorFaults | dict[str, Any] | None = None, config: ShredConfig = ShredConfig()) -> None:
        self.dataset, self.layout = dataset, np.asarray(layout, dtype=np.int64)
        self.noise_level, self.faults, self.config = float(noise_level), SensorFaults.from_any(faults), config
        self.network: ShredNetwork | None = None
        self.fit_seconds = float("nan")
        self.epochs_run = 0
        self.validation_loss: float | None = None

    def _inputs(self, readings: np.ndarray, mu: np.ndarray) -> torch.Tensor:
        """(E, n_t, 2m + 2): standardized readings (0 where missing), presence flags, standardized mu, and the
        frame's time since the start in [0, 1]."""
        present = np.isfinite(readings)
        scaled = np.where(present, (readings - self._reading_mean) / self._reading_std, 0.0)
        episodes, n_t = readings.shape[:2]
        mu_col = np.broadcast_to(((mu - self._mu_mean) / self._mu_std)[:, None, None], (episodes, n_t, 1))
        # the episode's own time axis, so that a history cut at frame k (reconstruct_frame) keeps its times
        time_col = np.broadcast_to(np.linspace(0.0, 1.0, self.dataset.n_frames)[None, :n_t, None], (episodes, n_t, 1))
        return torch.as_tensor(np.concatenate([scaled, present, mu_col, time_col], axis=2), dtype=torch.float32)

    def _windows(self, inputs: torch.Tensor, frames: np.ndarray) -> torch.Tensor:
        """The history window of each frame k in ``frames`` (readings of frames max(1, k - lags + 1)..k), zero
        before frame 1: (E * len(frames), lags, n_inputs), episode-major."""
        lags = self.config.lags
        padded = torch.cat([torch.zeros(inputs.shape[0], lags, inputs.shape[2]), inputs[:, 1:]], dim=1)
        # frame k's window ends at padded index lags + k - 1
        index = torch.as_tensor(frames)[:, None] + torch.arange(lags)[None, :]
        return padded[:, index].reshape(-1, lags, inputs.shape[2])

    def _standardized(self, fields: np.ndarray) -> torch.Tensor:
        flat = torch.as_tensor(fields, dtype=torch.float64).flatten(1 - len(self._field_shape))  # (..., C, cells)
        return ((flat - self._field_mean) / self._field_std).float().flatten(-2)

    @torch_threads("train")
    def fit(self, progress: bool = False) -> "Shred":
        """Train on the training split (see the module docstring); returns self."""
        from tqdm.auto import tqdm

        cfg, ds = self.config, self.dataset
        tic = time.perf_counter()
        torch.manual_seed(cfg.seed)
        rng = np.random.default_rng(cfg.seed)
        n_train = ds.n_trajectories("train")
        if n_train < 2:
            raise ValueError(f"SHRED needs at least 2 training trajectories (one held out), {ds.path} has {n_train}")
        fields = np.asarray(ds.fields("train"), dtype=np.float32)  # (N, n_t, C, *grid)
        self._field_shape = fields.shape[2:]
        snapshots = torch.as_tensor(fields.reshape(-1, *self._field_shape), dtype=torch.float64)
        self._field_mean = snapshots.mean(0).flatten(1)[None]  # (1, C, cells)
        self._field_std = torch.as_tensor(np.asarray(ds.stats_std, dtype=np.float64))[None, :, None]
        X = self._standardized(fields.reshape(-1, *self._field_shape)).double()
        # POD modes from the snapshot Gram matrix (deterministic eigh, no random SVD) of at most 2000 snapshots.
        basis = X[:: -(-X.shape[0] // 2000)]
        rank = min(cfg.rank, basis.shape[0] - 1, X.shape[1])
        eigvals, eigvecs = torch.linalg.eigh(basis @ basis.T)
        order = torch.argsort(eigvals, descending=True)[:rank]
        modes = (basis.T @ eigvecs[:, order]) / eigvals[order].clamp_min(1e-300).sqrt()  # (features, rank), orthonormal
        self._modes = modes.float()
        coefficients = (X.float() @ self._modes).reshape(n_train, ds.n_frames, rank)

        seeds = range(cfg.noise_seeds)
        trajectories = np.tile(np.arange(n_train), len(seeds))
        noise = np.repeat(np.asarray(list(seeds)) + 1_000_003, n_train)  # training noise, not the test seeds'
        readings = read_episodes(ds, self.layout, trajectories, noise, split="train",
                                 noise_level=self.noise_level, faults=self.faults)
        self._reading_mean = np.nan_to_num(np.nanmean(readings, axis=(0, 1)))  # a missing reading is NaN
        self._reading_std = np.nan_to_num(np.nanstd(readings, axis=(0, 1)), nan=1.0) + 1e-12
        mu = ds.params("train")[trajectories]
        self._mu_mean, self._mu_std = float(mu.mean()), float(mu.std()) + 1e-12
        frames = np.arange(1, ds.n_frames)
        inputs = self._windows(self._inputs(readings, mu), frames)  # (E * (n_t - 1), lags, 2m + 2)
        targets = coefficients[torch.as_tensor(trajectories)][:, 1:].reshape(-1, rank)

        held = rng.permutation(n_train)[: max(1, n_train // 10)]
        is_held = np.repeat(np.isin(trajectories, held), len(frames))
        train_x, train_y = inputs[~is_held], targets[~is_held]
        val_x, val_y = inputs[is_held], targets[is_held]
        self.network = ShredNetwork(inputs.shape[2], rank, cfg)
        optimizer = torch.optim.Adam(self.network.parameters(), lr=cfg.lr)
        generator = torch.Generator().manual_seed(cfg.seed)
        best, best_state, waited = float("inf"), None, 0
        bar = tqdm(range(cfg.epochs), desc="SHRED", unit="epoch", leave=False, disable=not progress)
        for epoch in bar:
            self.network.train()
            for batch in torch.randperm(len(train_x), generator=generator).split(cfg.batch_size):
                optimizer.zero_grad()
                loss = nn.functional.mse_loss(self.network(train_x[batch]), train_y[batch])
                loss.backward()
                optimizer.step()
            self.network.eval()
            with torch.no_grad():
                val = float(nn.functional.mse_loss(self.network(val_x), val_y))
            bar.set_postfix(val=f"{val:.3e}")
            self.epochs_run = epoch + 1
            if val < best:
                best, waited = val, 0
                best_state = {k: v.clone() for k, v in self.network.state_dict().items()}
            else:
                waited += 1
                if waited >= cfg.patience:
                    break
        bar.close()
        self.network.load_state_dict(best_state)
        self.network.eval()
        self.validation_loss = best
        self.fit_seconds = time.perf_counter() - tic
        return self

    def _fields(self, coefficients: torch.Tensor) -> np.ndarray:
        """Physical fields (n, C, *grid) from POD coefficients (n, rank)."""
        flat = (coefficients.double() @ self._modes.double().T).reshape(len(coefficients), *self._field_mean.shape[1:])
        return (flat * self._field_std + self._field_mean).reshape(-1, *self._field_shape).numpy()

    @torch_threads("assimilate")
    def reconstruct(self, readings: np.ndarray, mu: np.ndarray) -> np.ndarray:
        """Fields (E, n_t, C, *grid) of episodes' readings (E, n_t, m) (NaN where missing) with parameters (E,).
        Frame 0 (no reading used) is the training mean field."""
        if self.network is None:
            raise RuntimeError("call fit() before reconstruct()")
        readings = np.asarray(readings, dtype=np.float64)
        if readings.ndim != 3 or readings.shape[2] != len(self.layout) or readings.shape[1] > self.dataset.n_frames:
            raise ValueError(f"readings must be (episodes, frames <= {self.dataset.n_frames}, {len(self.layout)}), "
                             f"got {readings.shape}")
        episodes, n_t = readings.shape[:2]
        frames = np.arange(1, n_t)
        with torch.no_grad():
            coefficients = self.network(self._windows(self._inputs(readings, np.asarray(mu, dtype=np.float64)),
                                                      frames))
        out = np.empty((episodes, n_t, *self._field_shape), dtype=np.float32)
        out[:, 0] = self._fields(torch.zeros(1, self._modes.shape[1]))[0]
        out[:, 1:] = self._fields(coefficients).reshape(episodes, n_t - 1, *self._field_shape)
        return out

    @torch_threads("assimilate")
    def reconstruct_frame(self, history: np.ndarray, mu: float) -> np.ndarray:
        """The field (C, *grid) at frame k from the readings of frames 1..k, ``history`` (k, m) (NaN where missing),
        of an episode with parameter ``mu``: what :meth:`reconstruct` gives at frame k, from the past alone."""
        if self.network is None:
            raise RuntimeError("call fit() before reconstruct_frame()")
        history = np.asarray(history, dtype=np.float64)
        k = len(history)
        if history.ndim != 2 or history.shape[1] != len(self.layout) or not 1 <= k < self.dataset.n_frames:
            raise ValueError(f"history must be (k, {len(self.layout)}) with 1 <= k < {self.dataset.n_frames}, "
                             f"got {history.shape}")
        readings = np.concatenate([np.full((1, len(self.layout)), np.nan), history])[None]  # frame 0 is not read
        with torch.no_grad():
            coefficients = self.network(self._windows(self._inputs(readings, np.array([mu], dtype=np.float64)),
                                                      np.array([k])))
        return self._fields(coefficients)[0]

    def project(self, fields: np.ndarray) -> np.ndarray:
        """The rank-``rank`` POD projection of ``fields`` (E, n_t, C, *grid), the best this SHRED can output:
        its error is SHRED's floor."""
        X = self._standardized(fields.reshape(-1, *self._field_shape))
        return self._fields(X @ self._modes).reshape(fields.shape)

    def describe(self) -> dict[str, Any]:
        """The settings and the training outcome, for a results record."""
        return {"name": "shred", **asdict(self.config), "layout": [int(c) for c in self.layout],
                "epochs_run": self.epochs_run, "fit_seconds": self.fit_seconds,
                "validation_loss": self.validation_loss,
                "faults": None if self.faults is None else asdict(self.faults)}

