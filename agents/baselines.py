"""Static placement baselines: the paper layout, random layouts, QR pivoting on POD modes, greedy placement.

What each costs to compute (n cells, N snapshots, r POD modes, m sensors, n_c candidates, T training
trajectories of n_t frames):

=========== ======================================================================================
paper       the benchmark's geometric rule, O(m); no data.
random      one seeded draw without replacement, O(n); no data.
qr          POD of the observed channel on the training split, O(N n min(N, n)) for the Gram matrix and
            its eigendecomposition, then QR with column pivoting on the r x n mode matrix, O(n r^2)
            (scipy's pivoted QR, or cost-constrained QR with a cost map that forbids solid cells,
            O(n r m); both pick the sensors PySensors' ``QR`` / ``CCQR`` pick, which the tests check).
            Seconds on every benchmark; no model, no filter.
greedy      m rounds; round j scores each of the remaining n_c - j + 1 candidates added to the j - 1 chosen.
 "error"    runs the real filter for every (candidate, trajectory) pair: about m n_c T filter runs of n_t steps
            (batched as one filter per round), the most faithful and the most expensive objective.
 "trace"    the EKF analysis covariance linearized along the encoded training trajectories, mapped to the
            decoded field (the MSE the filter expects): T n_t encoder passes and r T n_t decoder
            Jacobian-vector products once, then m n_c T n_t Riccati steps of r x r matrices (no decoding
            per layout). Blind to the model's own errors: it scores what the filter believes, not what
            it achieves.
d-optimal   greedy on log det of the information the episode's readings give about the initial latent
            state (the linearized latent map, no process noise; exact for the Koopman model's linear map):
            the same linearization as "trace", then each cell's episode information once (T n_t n_c r^2),
            and m n_c T determinants of r x r matrices: no filter run per layout.
=========== ======================================================================================
"""

from __future__ import annotations

from typing import Any, Callable

import numpy as np
import scipy.linalg
import torch

from dks_gym.dataset import Dataset

from .policies import PlacementTask, StaticPolicy, candidate_lattice
from .scoring import (
    covariance_traces,
    episode_information,
    information_logdets,
    linearized,
    run_layouts,
)

# A CCQR cost larger than any row norm of an orthonormal basis (<= 1): cells with it are never pivots.
FORBIDDEN_COST = 1e6


class PaperLayout(StaticPolicy):
    """The paper's layout (SPEC section 2): ``Benchmark.paper_layout(m)``, from the geometry alone. Under a
    candidate constraint each sensor moves to the nearest allowed cell not taken yet (grid distance)."""

    name = "paper"

    def choose(self, task: PlacementTask) -> np.ndarray:
        layout = task.benchmark.paper_layout(task.n_sensors)
        if task.candidates is None:
            return layout
        grid = task.benchmark.grid
        allowed = np.stack(np.unravel_index(task.allowed_cells, grid), axis=1).astype(float)
        taken = np.zeros(len(allowed), dtype=bool)
        out = []
        for cell in layout:
            distance = np.linalg.norm(allowed - np.array(np.unravel_index(cell, grid), dtype=float), axis=1)
            distance[taken] = np.inf
            best = int(np.argmin(distance))
            taken[best] = True
            out.append(int(task.allowed_cells[best]))
        return np.asarray(out, dtype=np.int64)


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


def qr_pivots(basis: np.ndarray, n_pivots: int) -> np.ndarray:
    """The first ``n_pivots`` cells (rows of ``basis``, (n, r)) chosen by QR with column pivoting of basis^T.

    LAPACK's pivoted QR (geqp3) through scipy, called as PySensors' ``QR`` optimizer calls it; only the
    first r pivots are ranked, so ``n_pivots <= r``.
    """
    n, r = basis.shape
    if not 0 < n_pivots <= min(n, r):
        raise ValueError(f"n_pivots must be in [1, {min(n, r)}] for a basis of shape {basis.shape}, got {n_pivots}")
    # mode="r" skips forming Q; geqp3 runs the same, so the pivots are PySensors' (which forms Q).
    _, pivots = scipy.linalg.qr(basis.conj().T, mode="r", pivoting=True)
    return np.asarray(pivots[:n_pivots], dtype=np.int64)


def ccqr_pivots(basis: np.ndarray, costs: np.ndarray, n_pivots: int) -> np.ndarray:
    """The first ``n_pivots`` cells chosen by cost-constrained QR (Clark et al. 2018) on basis^T, (n, r).

    Householder QR of R = basis^T whose pivot at step j is the remaining column maximizing
    ||R[j:, i]|| - costs[i] instead of ||R[j:, i]||: with costs 0 it is plain greedy QR pivoting, and a
    cost above every column norm (<= 1 for an orthonormal basis) keeps a cell out while any other is
    left. The arithmetic is PySensors' ``CCQR`` step for step (same norms, reflector and update), so ties
    and near-ties resolve the same way; the pivots are greedy, so stopping after ``n_pivots`` steps
    changes none of them.
    """
    n, r = basis.shape
    costs = np.asarray(costs, dtype=np.float64)
    if costs.shape != (n,):
        raise ValueError(f"costs must have shape ({n},) (one per cell), got {costs.shape}")
    if not 0 < n_pivots <= min(n, r):
        raise ValueError(f"n_pivots must be in [1, {min(n, r)}] for a basis of shape {basis.shape}, got {n_pivots}")
    R = basis.conj().T.copy()  # (r, n): its columns are the candidate cells
    p = np.arange(n)
    for j in range(n_pivots):
        sub = R[j:, j:]
        norms = np.sqrt(np.sum(np.abs(sub) ** 2, axis=0))
        i = int(np.argmax(norms - costs[p[j:]]))
        zero_pivot = not norms[i] > 0
        if zero_pivot:
            # Every remaining allowed column is exactly zero (the basis is exhausted on the allowed
            # cells). PySensors then takes the pivot column itself as u, a view into R, and sets its
            # first entry to sqrt(2); the swap below moves that view's contents, so its update uses the
            # column swapped in. Reproduced as is, so that even these arbitrary picks stay PySensors'.
            sub[0, i] = np.sqrt(2)
        else:
            # Householder vector u with (I - u u^T) x = -sign(x_0) ||x|| e_0 for the pivot column x,
            # scaled so that u^T u = 2 (PySensors' normalization, kept for identical rounding).
            u = sub[:, i] / norms[i]
            u[0] += np.sign(u[0]) + (u[0] == 0)
            u /= np.sqrt(abs(u[0]))
        p[[j, j + i]] = p[[j + i, j]]
        R[:, [j, j + i]] = R[:, [j + i, j]]
        if zero_pivot:
            u = R[j:, j + i].copy()
        R[j:, j:] -= np.outer(u, np.dot(u, R[j:, j:]))  # np.dot as PySensors writes it: the same BLAS call
        R[j + 1 :, j] = 0
    return p[:n_pivots].copy()


class QRLayout(StaticPolicy):
    """QR column pivoting on the POD basis of the observed channel (Manohar et al. 2018).

    The basis is the leading ``n_modes`` (default m) POD modes of the mean-subtracted training snapshots
    of the observed channel. ``optimizer="auto"`` uses plain pivoted QR (:func:`qr_pivots`) when every
    cell is allowed and cost-constrained QR (:func:`ccqr_pivots`) with a cost map otherwise (solid cells,
    or cells outside ``candidates``, cost ``FORBIDDEN_COST``, so they are never chosen); ``"ccqr"`` forces
    the latter. QR ranks only as many sensors as there are modes, so ``n_modes >= m``. The layouts equal
    PySensors' ``SSPOR`` with its ``QR`` / ``CCQR`` optimizers (tests/test_agents.py checks both).
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
        self.used_ccqr = use_ccqr
        return ccqr_pivots(U, costs, m) if use_ccqr else qr_pivots(U, m)

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


#: Greedy objectives and the policy names they go by.
GREEDY_OBJECTIVES = {"error": "greedy", "trace": "greedy-trace", "information": "d-optimal"}


def greedy_layout(score: Callable[[np.ndarray], np.ndarray], candidates: np.ndarray,
                  n_sensors: int) -> tuple[np.ndarray, list[float], list[np.ndarray]]:
    """Add one sensor at a time, each time the candidate whose layout ``score`` (lower is better) rates best.

    ``score`` maps (L, j) layouts to (L,) values. Returns the layout, the best value after each round and
    every candidate's value per round.
    """
    chosen: list[int] = []
    history, scores = [], []
    for _ in range(n_sensors):
        pool = np.setdiff1d(candidates, chosen)
        layouts = np.concatenate([np.repeat(np.asarray(chosen, dtype=np.int64)[None], len(pool), 0),
                                  pool[:, None]], axis=1)
        values = score(layouts)
        best = int(np.argmin(values))
        chosen.append(int(pool[best]))
        history.append(float(values[best]))
        scores.append(values)
    return np.asarray(chosen, dtype=np.int64), history, scores


class GreedyLayout(StaticPolicy):
    """Add one sensor at a time, each time the candidate that most lowers the objective on training trajectories.

    ``objective="error"``: the filter's own time-averaged MSE (frames 1..n_t-1, physical units) from real
    filter runs with the task's filter settings on the training split (its own noise realization).
    ``objective="trace"``: the time-averaged trace of the EKF analysis covariance linearized along the
    encoded training trajectories, as the variance of the decoded scored field
    (:func:`~dks_gym_agents.scoring.covariance_traces`, ``space="field"``); it can only fall as sensors are added.
    ``objective="information"`` (the "d-optimal" policy): minus the mean log det of the information the
    episode's readings give about the initial latent state, prior P0^{-1}
    (:func:`~dks_gym_agents.scoring.episode_information`); monotone and submodular in the layout, so the greedy
    layout is within (1 - 1/e) of the best one's gain over the prior. Candidates: ``candidates`` or
    :func:`~dks_gym_agents.policies.candidate_lattice` of ``n_candidates`` (default max(32, 2m)) allowed
    cells; trajectories: ``n_trajectories`` spread over the training parameters. ``history`` holds the best
    objective after each round, ``scores`` every candidate's score per round. ``max_batch`` caps the
    (layout, trajectory) pairs filtered at once.
    """

    def __init__(self, objective: str = "error", n_candidates: int | None = None, n_trajectories: int | None = None,
                 candidates: np.ndarray | None = None, max_batch: int = 256) -> None:
        super().__init__()
        if objective not in GREEDY_OBJECTIVES:
            raise ValueError(f"objective must be one of {', '.join(GREEDY_OBJECTIVES)}, got {objective!r}")
        self.objective = objective
        self.name = GREEDY_OBJECTIVES[objective]
        self.n_candidates = None if n_candidates is None else int(n_candidates)
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
        scorer = {"error": lambda: self._error_scorer(task, trajectories),
                  "trace": lambda: self._trace_scorer(task, cands, trajectories),
                  "information": lambda: self._information_scorer(task, cands, trajectories)}[self.objective]
        chosen, self.history, self.scores = greedy_layout(scorer(), cands, task.n_sensors)
        return chosen

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
        lin = linearized(task.model, task.dataset, trajectories, cands, task.config)
        per_call = max(1, (4 * self.max_batch) // len(trajectories))

        def score(layouts: np.ndarray) -> np.ndarray:
            return np.concatenate([covariance_traces(lin, layouts[s:s + per_call], task.config).mean(axis=(1, 2))
                                   for s in range(0, len(layouts), per_call)])

        return score

    def _information_scorer(self, task: PlacementTask, cands: np.ndarray, trajectories: np.ndarray):
        lin = linearized(task.model, task.dataset, trajectories, cands, task.config)
        information = episode_information(lin)
        r = information.shape[-1]
        P0 = torch.as_tensor(task.config.filter.initial_covariance(task.model), dtype=information.dtype)
        prior = torch.linalg.inv(P0 if P0.ndim == 2 else P0 * torch.eye(r, dtype=information.dtype))

        def score(layouts: np.ndarray) -> np.ndarray:  # lower is better: minus the mean log det
            return -information_logdets(lin, information, layouts, prior).mean(axis=1)

        return score

    def describe(self) -> dict[str, Any]:
        used = getattr(self, "used_candidates", None)
        out = dict(super().describe(), objective=self.objective,
                   n_candidates=self.n_candidates if used is None else len(used),
                   n_trajectories=self.n_trajectories, history=self.history)
        if getattr(self, "used_trajectories", None) is not None:
            out["trajectories"] = self.used_trajectories.tolist()
            out["candidates"] = self.used_candidates.tolist()
        return out
