"""Static placement baselines: the paper layout, random layouts, QR pivoting on POD modes, greedy placement.

What each costs to compute (n cells, N snapshots, r POD modes, m sensors, n_c candidates, T training
trajectories of n_t frames):

=========== ======================================================================================
paper       the benchmark's geometric rule, O(m); no data.
random      one seeded draw without replacement, O(n); no data.
qr          POD of the observed channel on the training split, O(N n min(N, n)) for the Gram matrix and
            its eigendecomposition, then QR with column pivoting on the r x n mode matrix, O(n r^2)
            (PySensors ``SSPOR`` with ``QR``, or ``CCQR`` with a cost map that forbids solid cells).
            Seconds on every benchmark; no model, no filter.
greedy      m rounds; round j scores each of the remaining n_c - j + 1 candidates added to the j - 1 chosen.
 "error"    runs the real filter for every (candidate, trajectory) pair: about m n_c T filter runs of n_t steps
            (batched as one filter per round), the most faithful and the most expensive objective.
 "trace"    the EKF analysis covariance linearized along the encoded training trajectories, mapped to the
            decoded field (the MSE the filter expects): T n_t encoder passes and r T n_t decoder
            Jacobian-vector products once, then m n_c T n_t Riccati steps of r x r matrices (no decoding
            per layout). Blind to the model's own errors: it scores what the filter believes, not what
            it achieves.
=========== ======================================================================================
"""

from __future__ import annotations

from typing import Any

import numpy as np

from dks_gym.dataset import Dataset

from .policies import PlacementTask, StaticPolicy, candidate_lattice
from .scoring import LinearizedTrajectories, covariance_traces, run_layouts

# A CCQR cost larger than any row norm of an orthonormal basis (<= 1): cells with it are never pivots.
FORBIDDEN_COST = 1e6


class PaperLayout(StaticPolicy):
    """The paper's layout (SPEC section 2): ``Benchmark.paper_layout(m)``, from the geometry alone."""

    name = "paper"

    def choose(self, task: PlacementTask) -> np.ndarray:
        return task.benchmark.paper_layout(task.n_sensors)


class RandomLayout(StaticPolicy):
    """m distinct cells drawn uniformly without replacement from the allowed cells, seeded."""

    def __init__(self, seed: int = 0) -> None:
        super().__init__()
        self.seed = int(seed)
        self.name = f"random-{self.seed}"

    def choose(self, task: PlacementTask) -> np.ndarray:
        rng = np.random.default_rng(self.seed)
        return np.sort(rng.choice(task.allowed_cells, size=task.n_sensors, replace=False))

    def describe(self) -> dict[str, Any]:
        return dict(super().describe(), seed=self.seed)


def observed_snapshots(dataset: Dataset, max_snapshots: int = 5000, split: str = "train") -> np.ndarray:
    """The observed channel of the split as a snapshot matrix (N, n_cells), float32.

    Frames are taken evenly in time from every trajectory so that N <= ``max_snapshots``.
    """
    n_traj, n_t = dataset.n_trajectories(split), dataset.n_frames
    per_traj = max(1, min(n_t, max_snapshots // n_traj))
    frames = np.unique(np.linspace(0, n_t - 1, per_traj).round().astype(int))
    c = dataset.benchmark.observed_index
    fields = dataset.fields(split)
    rows = [np.asarray(fields[i, :, c], dtype=np.float32)[frames].reshape(len(frames), -1) for i in range(n_traj)]
    return np.concatenate(rows)


def pod_modes(snapshots: np.ndarray, n_modes: int) -> tuple[np.ndarray, np.ndarray]:
    """The leading ``n_modes`` POD modes (n_cells, n_modes) and singular values of *centred* snapshots (N, n_cells).

    Eigendecomposition of the smaller Gram matrix in float64 (cells x cells, or snapshots x snapshots by
    the method of snapshots). Raises if the data hold fewer than ``n_modes`` independent modes.
    """
    X = np.asarray(snapshots, dtype=np.float64)
    n_snap, n_cells = X.shape
    if n_cells <= n_snap:
        lam, V = np.linalg.eigh(X.T @ X)
        lam, U = lam[::-1], V[:, ::-1]
    else:
        lam, V = np.linalg.eigh(X @ X.T)
        lam, V = lam[::-1], V[:, ::-1]
        U = X.T @ V[:, :n_modes] / np.sqrt(np.clip(lam[:n_modes], 1e-300, None))
    lam = np.clip(lam, 0, None)
    rank = int(np.sum(lam > 1e-10 * max(lam[0], 1e-300)))
    if rank < n_modes:
        raise ValueError(
            f"the training snapshots hold only {rank} POD modes, fewer than n_modes={n_modes}; "
            "use fewer modes (and sensors) or more training data"
        )
    return U[:, :n_modes], np.sqrt(lam[:n_modes])


class QRLayout(StaticPolicy):
    """QR column pivoting on the POD basis of the observed channel (Manohar et al. 2018), through PySensors.

    The basis is the leading ``n_modes`` (default m) POD modes of the mean-subtracted training snapshots
    of the observed channel. ``optimizer="auto"`` uses ``ps.optimizers.QR`` when every cell is allowed
    and ``ps.optimizers.CCQR`` with a cost map otherwise (solid cells, or cells outside ``candidates``,
    cost ``FORBIDDEN_COST``, so they are never chosen); ``"ccqr"`` forces the latter. QR ranks only as
    many sensors as there are modes, so ``n_modes >= m``.
    """

    name = "qr"

    def __init__(self, n_modes: int | None = None, optimizer: str = "auto", max_snapshots: int = 5000) -> None:
        super().__init__()
        if optimizer not in ("auto", "qr", "ccqr"):
            raise ValueError(f"optimizer must be 'auto', 'qr' or 'ccqr', got {optimizer!r}")
        self.n_modes = n_modes
        self.optimizer = optimizer
        self.max_snapshots = int(max_snapshots)
        self.singular_values: np.ndarray | None = None

    def choose(self, task: PlacementTask) -> np.ndarray:
        import pysensors as ps

        m = task.n_sensors
        r = m if self.n_modes is None else int(self.n_modes)
        if r < m:
            raise ValueError(f"n_modes={r} < n_sensors={m}: QR pivoting ranks only as many sensors as modes")
        X = observed_snapshots(task.dataset, self.max_snapshots)
        X = X - X.mean(axis=0, keepdims=True)
        U, self.singular_values = pod_modes(X, r)
        costs = np.full(task.benchmark.n_cells, FORBIDDEN_COST)
        costs[task.allowed_cells] = 0.0
        constrained = bool(np.any(costs > 0))
        if self.optimizer == "qr" and constrained:
            raise ValueError("some cells are forbidden (solid or not candidates): use optimizer='ccqr' or 'auto'")
        use_ccqr = self.optimizer == "ccqr" or (self.optimizer == "auto" and constrained)
        optimizer = ps.optimizers.CCQR(sensor_costs=costs) if use_ccqr else ps.optimizers.QR()
        sspor = ps.SSPOR(basis=ps.basis.Custom(U=U, n_basis_modes=r), optimizer=optimizer, n_sensors=m)
        sspor.fit(X, quiet=True, seed=task.seed)
        self.used_ccqr = use_ccqr
        return np.asarray(sspor.get_selected_sensors(), dtype=np.int64)

    def describe(self) -> dict[str, Any]:
        return dict(super().describe(), n_modes=self.n_modes, optimizer=self.optimizer,
                    max_snapshots=self.max_snapshots)


def spread_trajectories(dataset: Dataset, n: int | None, split: str = "train") -> np.ndarray:
    """``n`` trajectories of the split spread evenly over its parameter range (all of them for None)."""
    n_traj = dataset.n_trajectories(split)
    order = np.argsort(dataset.params(split), kind="stable")
    if n is None or n >= n_traj:
        return np.sort(order)
    return np.sort(order[np.unique(np.linspace(0, n_traj - 1, n).round().astype(int))])


class GreedyLayout(StaticPolicy):
    """Add one sensor at a time, each time the candidate that most lowers the objective on training trajectories.

    ``objective="error"``: the filter's own time-averaged MSE (frames 1..n_t-1, physical units) from real
    filter runs with the task's filter settings on the training split (its own noise realization).
    ``objective="trace"``: the time-averaged trace of the EKF analysis covariance linearized along the
    encoded training trajectories, as the variance of the decoded scored field
    (:func:`~dks_gym_agents.scoring.covariance_traces`, ``space="field"``); it can only fall as sensors are added.
    Candidates: ``candidates`` or a lattice of about ``n_candidates`` allowed cells; trajectories:
    ``n_trajectories`` spread over the training parameters. ``history`` holds the best objective after
    each round, ``scores`` every candidate's score per round. ``max_batch`` caps the (layout, trajectory)
    pairs filtered at once.
    """

    def __init__(self, objective: str = "error", n_candidates: int = 32, n_trajectories: int | None = None,
                 candidates: np.ndarray | None = None, max_batch: int = 256) -> None:
        super().__init__()
        if objective not in ("error", "trace"):
            raise ValueError(f"objective must be 'error' or 'trace', got {objective!r}")
        self.objective = objective
        self.name = "greedy" if objective == "error" else "greedy-trace"
        self.n_candidates = int(n_candidates)
        self.n_trajectories = n_trajectories if n_trajectories is not None else (4 if objective == "error" else 10)
        self.candidates = None if candidates is None else np.asarray(candidates, dtype=np.int64)
        self.max_batch = int(max_batch)
        self.history: list[float] = []
        self.scores: list[np.ndarray] = []
        self.filter_element_steps = 0

    def choose(self, task: PlacementTask) -> np.ndarray:
        cands = self.candidates if self.candidates is not None else candidate_lattice(task, self.n_candidates)
        PlacementTask(task.dataset, task.model, task.config, candidates=cands)  # validates them
        self.used_candidates = cands
        trajectories = spread_trajectories(task.dataset, self.n_trajectories)
        self.used_trajectories = trajectories
        score = self._trace_scorer(task, cands, trajectories) if self.objective == "trace" else \
            self._error_scorer(task, trajectories)
        chosen: list[int] = []
        self.history, self.scores = [], []
        for _ in range(task.n_sensors):
            pool = np.setdiff1d(cands, chosen)
            layouts = np.concatenate([np.repeat(np.asarray(chosen, dtype=np.int64)[None], len(pool), 0),
                                      pool[:, None]], axis=1)
            values = score(layouts)
            best = int(np.argmin(values))
            chosen.append(int(pool[best]))
            self.history.append(float(values[best]))
            self.scores.append(values)
        return np.asarray(chosen, dtype=np.int64)

    def _error_scorer(self, task: PlacementTask, trajectories: np.ndarray):
        n_traj = len(trajectories)
        per_call = max(1, self.max_batch // n_traj)

        def score(layouts: np.ndarray) -> np.ndarray:
            out = []
            for s in range(0, len(layouts), per_call):
                chunk = layouts[s:s + per_call]
                result = run_layouts(task.model, task.dataset, np.repeat(chunk, n_traj, axis=0),
                                     np.tile(trajectories, len(chunk)), task.config, split="train")
                self.filter_element_steps += result.batch * (result.step_mse.shape[1] - 1)
                out.append(result.step_mse[:, 1:].mean(axis=1).reshape(len(chunk), n_traj).mean(axis=1))
            return np.concatenate(out)

        return score

    def _trace_scorer(self, task: PlacementTask, cands: np.ndarray, trajectories: np.ndarray):
        lin = LinearizedTrajectories(task.model, task.dataset, trajectories, cands, task.config)
        per_call = max(1, (4 * self.max_batch) // len(trajectories))

        def score(layouts: np.ndarray) -> np.ndarray:
            return np.concatenate([covariance_traces(lin, layouts[s:s + per_call], task.config).mean(axis=(1, 2))
                                   for s in range(0, len(layouts), per_call)])

        return score

    def describe(self) -> dict[str, Any]:
        out = dict(super().describe(), objective=self.objective, n_candidates=self.n_candidates,
                   n_trajectories=self.n_trajectories, history=self.history)
        if getattr(self, "used_trajectories", None) is not None:
            out["trajectories"] = self.used_trajectories.tolist()
            out["candidates"] = self.used_candidates.tolist()
        return out
