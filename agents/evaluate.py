"""The placement evaluation harness: every policy on the test split, identical noise, one ranked table.

:func:`evaluate_placement` (and ``dks-gym evaluate-placement``) fits each policy on the training split,
then filters every test trajectory with its layouts as one batch (static policies: one layout per episode,
:func:`~dks_gym_agents.scoring.run_layouts`; adaptive ones: a layout per step, :func:`~dks_gym_agents.scoring.run_adaptive`).
The measurement noise depends only on (noise seed, split, trajectory, frame, cell), so every policy is
judged on the same noise realization, and a cell read by two policies reads the same value.

Outputs in ``out``:

* ``placement.json``: a results document of the ``dks-gym-results`` schema (:mod:`dks_gym.evaluation.results`),
  one record per policy with ``experiment = "placement/<policy>"``, plus the placement fields ``policy``,
  ``adaptive``, ``sensors`` (static layout) or ``sensor_counts`` (adaptive: [cell, reads]),
  ``time_mean_mse_mean``/``_std``, ``per_trajectory_time_mean_mse``, ``fit_seconds`` (fitting here),
  ``offline_seconds`` (the offline cost: fitting plus the training recorded in a loaded agent checkpoint),
  ``decision_seconds`` (wall time per decision: per episode for static layouts, per step and trajectory for
  adaptive ones) and ``policy_config``. A ``placement/forward`` record (no assimilation) is the reference.
* ``placement.md``: the ranked table (by time-averaged MSE; frames 1..n_t-1, frame 0 being the same
  initial estimate for all) with final-time and time-averaged MSE mean and std across *episodes* (an
  episode = one test trajectory under one noise seed, so the std mixes trajectory-to-trajectory and
  noise-to-noise spread), the per-episode (paired) ratio to the paper layout, the paired comparison with
  the random layouts (:func:`paired_vs_random`) and the costs.

With random layouts in the run, every record also gets ``paired_vs_random`` (:func:`add_paired_vs_random`,
which works on any results document, e.g. a committed ``placement.json``).
* ``placement_layouts.png``: each policy's layout over a snapshot of the observed field.
"""

from __future__ import annotations

import copy
import dataclasses
import json
import math
import platform
import time
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
import torch

from dks_gym.assimilation import AssimilationResult, field_errors
from dks_gym.envs import SensorFaults
from dks_gym.evaluation.results import UNCERTAINTY_SCORES, load_results, make_record, new_results, save_results
from dks_gym.models.shred import Shred, ShredConfig, read_episodes

from .adaptive import PPOAdaptive
from .baselines import GREEDY_OBJECTIVES, GreedyLayout, PaperLayout, QRLayout, RandomLayout
from .policies import AdaptivePolicy, PlacementPolicy, PlacementTask, StaticPolicy, constraint_candidates
from .scoring import run_adaptive, run_layouts
from .sequential import SequentialLayout

POLICIES = ("paper", "random", "qr", "greedy", "greedy-trace", "d-optimal", "sequential", "ppo")
#: The placement benchmark's fault scenario, the same on every benchmark: one reading in ten lost, and each
#: sensor failing for good with probability 0.5 % per step (about 40 % of them within a 100-frame episode).
DEFAULT_FAULTS = SensorFaults(dropout=0.1, failure_rate=0.005)


def make_policies(names: Sequence[str | PlacementPolicy] | str, *, random_seeds: int = 5,
                  greedy_candidates: int | None = None,
                  greedy_trajectories: int | None = None, sequential: str | Path | None = None,
                  ppo: str | Path | None = None, agent_timesteps: int | None = None,
                  agent_out: str | Path | None = None) -> list[PlacementPolicy]:
    """Policies by name ("paper", "random" (``random_seeds`` seeded layouts), "qr", "greedy" (filter error),
    "greedy-trace", "d-optimal", "sequential", "ppo") or given as :class:`PlacementPolicy` objects (your own, used as
    they are). Learned ones load ``sequential`` / ``ppo`` checkpoints when given, else train
    (``agent_timesteps`` steps, default each trainer's, checkpoints to ``agent_out``)."""
    if isinstance(names, str):
        names = [n.strip() for n in names.split(",") if n.strip()]
    unknown = [n for n in names if not isinstance(n, PlacementPolicy) and n not in POLICIES]
    if unknown or not names:
        raise ValueError(f"unknown policies {unknown}; choose from {', '.join(POLICIES)} (comma-separated) "
                         "or pass PlacementPolicy objects")
    steps = {} if agent_timesteps is None else {"timesteps": int(agent_timesteps)}
    out: list[PlacementPolicy] = []
    unique = [n for i, n in enumerate(names) if isinstance(n, PlacementPolicy) or n not in names[:i]]
    for name in unique:
        if isinstance(name, PlacementPolicy):
            out.append(name)
        elif name == "paper":
            out.append(PaperLayout())
        elif name == "random":
            out.extend(RandomLayout(seed) for seed in range(random_seeds))
        elif name == "qr":
            out.append(QRLayout())
        elif name in GREEDY_OBJECTIVES.values():
            objective = next(key for key, value in GREEDY_OBJECTIVES.items() if value == name)
            out.append(GreedyLayout(objective, n_candidates=greedy_candidates, n_trajectories=greedy_trajectories))
        elif name == "sequential":
            out.append(SequentialLayout(sequential, out=agent_out, **steps))
        else:
            out.append(PPOAdaptive(ppo, out=agent_out, **steps))
    names_seen = [p.name for p in out]
    clash = sorted({n for n in names_seen if names_seen.count(n) > 1})
    if clash:
        raise ValueError(f"two policies are named {clash}; give each policy a distinct name")
    return out


@dataclass
class PolicyResult:
    """One policy's test-split run: the batched filter result and the policy's costs and layouts."""

    policy: PlacementPolicy
    result: AssimilationResult
    layouts: np.ndarray  # (B, m) static; (B, n_t - 1, m) adaptive
    decision_seconds: float

    @property
    def name(self) -> str:
        return self.policy.name

    @property
    def time_mean_mse(self) -> np.ndarray:
        """(B,) MSE averaged over the assimilated frames 1..n_t-1."""
        return self.result.step_mse[:, 1:].mean(axis=1)


def episodes(task: PlacementTask, trajectories: np.ndarray | None = None,
             noise_seeds: Sequence[int] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The evaluation episodes: every trajectory (default: the whole split) under every noise seed (default:
    ``task.config.noise_seed``), as (trajectory, seed) arrays ordered seed-major."""
    n = task.dataset.n_trajectories(task.config.split)
    index = np.arange(n) if trajectories is None else np.asarray(trajectories, dtype=np.int64)
    seeds = [task.config.noise_seed] if noise_seeds is None else [int(s) for s in noise_seeds]
    return np.tile(index, len(seeds)), np.repeat(np.asarray(seeds, dtype=np.int64), len(index))


def evaluate_policy(task: PlacementTask, policy: PlacementPolicy, trajectories: np.ndarray | None = None,
                    noise_seeds: Sequence[int] | None = None) -> PolicyResult:
    """Fit ``policy`` on the training split (unless fitted) and run it on the test episodes (:func:`episodes`)."""
    ds, config = task.dataset, task.config
    index, seeds = episodes(task, trajectories, noise_seeds)
    if policy.task is None:
        policy.fit(task)
    if isinstance(policy, AdaptivePolicy):
        result = run_adaptive(task.model, ds, policy.decide, policy.candidates, index, config, noise_seeds=seeds)
        per_decision = float(result.extras["decision_seconds"].mean() / len(index))
        return PolicyResult(policy, result, result.extras["layouts"], per_decision)
    if not isinstance(policy, StaticPolicy):
        raise TypeError(f"{type(policy).__name__} is neither a StaticPolicy nor an AdaptivePolicy")
    tic = time.perf_counter()
    layouts = policy.episode_layouts(ds.params(config.split)[index])
    per_decision = (time.perf_counter() - tic) / len(index)
    result = run_layouts(task.model, ds, layouts, index, config, noise_seeds=seeds)
    return PolicyResult(policy, result, layouts, per_decision)


def frame_errors(estimate: np.ndarray, truth: np.ndarray, scored: Sequence[int]) -> np.ndarray:
    """Eq. 18 (:func:`~dks_gym.assimilation.field_errors`) at every frame of episodes of fields
    (E, n_t, C, *grid): (E, n_t), float64."""
    flat = [torch.as_tensor(np.asarray(x, dtype=np.float64).reshape(-1, *x.shape[2:])) for x in (estimate, truth)]
    return field_errors(*flat, tuple(scored)).numpy().reshape(estimate.shape[:2])


def evaluate_shred(task: PlacementTask, pr: PolicyResult, noise_seeds: Sequence[int],
                   config: ShredConfig = ShredConfig(), progress: bool = False) -> dict[str, Any]:
    """SHRED (:mod:`dks_gym.models.shred`) trained on the training split with the layout of a static policy's
    result ``pr`` and the task's noise and faults, scored on the same test episodes: a results record named
    ``shred-<policy>`` (model "shred", filter "none") with the placement fields, and ``pod_floor_time_mean_mse``,
    the error of the POD projection of the truth that bounds it."""
    if pr.policy.adaptive or not np.all(pr.layouts == pr.layouts[:1]):
        raise ValueError(f"SHRED reads one fixed layout; {pr.name!r} gives a layout per episode or per step")
    ds, cfg = task.dataset, task.config
    layout = pr.layouts[0]
    shred = Shred(ds, layout, noise_level=cfg.noise_level, faults=cfg.faults, config=config).fit(progress=progress)
    index, seeds = episodes(task, noise_seeds=noise_seeds)
    tic = time.perf_counter()
    readings = read_episodes(ds, layout, index, seeds, split=cfg.split, noise_level=cfg.noise_level,
                             faults=cfg.faults)
    estimate = shred.reconstruct(readings, ds.params(cfg.split)[index])
    seconds = time.perf_counter() - tic
    truth = np.stack([ds.trajectory(cfg.split, int(t)) for t in index])
    step = frame_errors(estimate, truth, task.benchmark.scored_indices)
    floor = frame_errors(shred.project(truth), truth, task.benchmark.scored_indices)[:, 1:].mean()
    final, tm = step[:, -1], step[:, 1:].mean(axis=1)
    rec: dict[str, Any] = {
        "experiment": f"placement/shred-{pr.name}", "model": "shred", "filter": "none", "initial": "approximate",
        "noise": float(cfg.noise_level), "r": int(shred.network.decoder[-1].out_features), "T": 1, "n_members": None,
        "batch": len(index), "final_mse_mean": float(final.mean()),
        "final_mse_std": float(final.std(ddof=1)) if len(final) > 1 else None,
        "per_step_mse_mean": [float(v) for v in step.mean(axis=0)],
        "per_trajectory_final_mse": [float(v) for v in final], "max_forecast_norm": None,
        "da_step_seconds": seconds / (ds.n_frames - 1), "wall_time": shred.fit_seconds + seconds,
        "trajectories": [int(t) for t in index], "params": [float(v) for v in ds.params(cfg.split)[index]],
        "per_trajectory_step_mse": [[float(v) for v in row] for row in step],
        **{f"final_{n}_mean": None for n in UNCERTAINTY_SCORES},
        "policy": f"shred-{pr.name}", "adaptive": False, "sensors": [int(c) for c in layout],
        "time_mean_mse_mean": float(tm.mean()), "time_mean_mse_std": float(tm.std(ddof=1)) if len(tm) > 1 else None,
        "per_trajectory_time_mean_mse": [float(v) for v in tm], "fit_seconds": shred.fit_seconds,
        "offline_seconds": shred.fit_seconds, "decision_seconds": None, "policy_config": shred.describe(),
        "noise_seeds": [int(s) for s in seeds], "pod_floor_time_mean_mse": float(floor),
    }
    return rec


def _record(pr: PolicyResult, task: PlacementTask) -> dict[str, Any]:
    rec = make_record(pr.result, experiment=f"placement/{pr.name}", keep_curves=True)
    tm = pr.time_mean_mse
    rec.update(
        policy=pr.name, adaptive=pr.policy.adaptive,
        time_mean_mse_mean=float(tm.mean()), time_mean_mse_std=float(tm.std(ddof=1)) if len(tm) > 1 else None,
        per_trajectory_time_mean_mse=[float(v) for v in tm],
        fit_seconds=None if not math.isfinite(pr.policy.fit_seconds) else float(pr.policy.fit_seconds),
        offline_seconds=None if not math.isfinite(pr.policy.offline_seconds) else float(pr.policy.offline_seconds),
        decision_seconds=float(pr.decision_seconds), policy_config=pr.policy.describe(),
        noise_seeds=[int(s) for s in pr.result.extras["noise_seeds"]],
    )
    if pr.policy.adaptive:
        cells, counts = np.unique(pr.layouts, return_counts=True)
        rec["sensors"] = None
        rec["sensor_counts"] = [[int(c), int(n)] for c, n in zip(cells, counts)]
        rec["candidates"] = [int(c) for c in pr.policy.candidates]
    else:
        rec["sensors"] = [int(c) for c in pr.layouts[0]]
    return rec


def placement_document(task: PlacementTask, results: Sequence[PolicyResult], forward: AssimilationResult | None,
                       *, model_preset: str, wall_time: float) -> dict[str, Any]:
    """The results document (``dks-gym-results`` schema) of one harness run."""
    from dks_gym.version import __version__
    from dks_gym.models.checkpoint import dataset_identity

    ds = task.dataset
    records = [_record(pr, task) for pr in results]
    if forward is not None:
        rec = make_record(forward, experiment="placement/forward", keep_curves=True)
        tm = forward.step_mse[:, 1:].mean(axis=1)
        rec.update(policy="forward", adaptive=False, sensors=None, time_mean_mse_mean=float(tm.mean()),
                   noise_seeds=[int(s) for s in forward.extras["noise_seeds"]],
                   time_mean_mse_std=float(tm.std(ddof=1)) if len(tm) > 1 else None,
                   per_trajectory_time_mean_mse=[float(v) for v in tm], fit_seconds=None, offline_seconds=None,
                   decision_seconds=None,
                   policy_config={"name": "forward", "note": "no assimilation: the open-loop model, sensors unused"})
        records.append(rec)
    seeds = sorted({int(s) for s in results[0].result.extras["noise_seeds"]})
    config = dict(task.config.as_record(), n_test=ds.n_trajectories(task.config.split), n_frames=ds.n_frames,
                  noise_seeds=seeds, n_episodes=int(results[0].result.batch),
                  observed_channel=ds.observed_channel, scored_channels=list(ds.scored_channels),
                  model=task.model.kind, r=int(task.model.r), model_preset=model_preset, device=str(task.device),
                  policies=[pr.name for pr in results], ranking="time-averaged MSE over frames 1..n_t-1",
                  n_allowed_cells=int(len(task.allowed_cells)), constrained=task.candidates is not None,
                  created=datetime.now(timezone.utc).isoformat(timespec="seconds"), wall_time_s=wall_time,
                  dks_gym_version=__version__, torch_version=torch.__version__, python=platform.python_version())
    return new_results(ds.benchmark.name, model_preset, dataset_identity(ds), config, records,
                       [{"model": task.model.kind, "r": int(task.model.r), "preset": model_preset}])


# Paired comparison with the random layouts -------------------------------------------------------------
def paired_vs_random(doc: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """Per policy: its time-averaged MSE against the mean of the random layouts on the same episode.

    For every episode e (trajectory x noise seed), ``q_e = log(MSE_policy(e) / mean_s MSE_random-s(e))``,
    the mean over the run's seeded random layouts of the same episode (same trajectory, same noise); for a
    ``random-s`` record the mean is over the *other* seeds. Returns ``{policy: {log_ratio_mean,
    log_ratio_se, log_ratio_se_trajectories, ratio_mean, wins, n_episodes, n_random}}``: ``log_ratio_se`` =
    std(q)/sqrt(episodes); ``log_ratio_se_trajectories`` the same over the per-trajectory means of q (the
    noise seeds of one trajectory are not independent episodes, so this is the conservative one);
    ``ratio_mean`` = mean of exp(q); ``wins`` = episodes where the policy's MSE is below the random mean.
    ``log_ratio_geometric_mean``/``_se``: the same against the per-episode *geometric* mean of the random
    layouts, i.e. the average paired log ratio against each random layout (the arithmetic mean is pulled up
    by the worst random layouts, so a typical random layout itself scores below 0 against it).
    Negative log ratios beat random. Empty without at least two random layouts. Works on any document
    from :func:`placement_document` (e.g. a committed ``placement.json``), old ones included.
    """
    recs = [r for r in doc["records"] if r["experiment"].startswith("placement/")]
    randoms = {r["policy"]: np.asarray(r["per_trajectory_time_mean_mse"], dtype=float)
               for r in recs if r["policy"].startswith("random-")}
    if len(randoms) < 2:
        return {}
    stack = np.stack(list(randoms.values()))
    total = stack.sum(axis=0)
    out: dict[str, dict[str, Any]] = {}
    for rec in recs:
        a = np.asarray(rec["per_trajectory_time_mean_mse"], dtype=float)
        if a.shape != total.shape:
            continue
        own = randoms.get(rec["policy"])
        ref = (total - own) / (len(randoms) - 1) if own is not None else total / len(randoms)
        q = np.log(a / ref)
        others = stack if own is None else np.stack([v for k, v in randoms.items() if k != rec["policy"]])
        g = np.log(a) - np.log(others).mean(axis=0)  # against the geometric mean = mean paired log ratio per seed
        n = len(q)
        traj = np.asarray(rec.get("trajectories", np.arange(n)))
        per_traj = np.array([q[traj == t].mean() for t in np.unique(traj)])
        out[rec["policy"]] = {
            "log_ratio_mean": float(q.mean()),
            "log_ratio_se": float(q.std(ddof=1) / math.sqrt(n)) if n > 1 else None,
            "log_ratio_se_trajectories": (float(per_traj.std(ddof=1) / math.sqrt(len(per_traj)))
                                          if len(per_traj) > 1 else None),
            "log_ratio_geometric_mean": float(g.mean()),
            "log_ratio_geometric_se": float(g.std(ddof=1) / math.sqrt(n)) if n > 1 else None,
            "ratio_mean": float(np.exp(q).mean()), "wins": int(np.sum(a < ref)), "n_episodes": n,
            "n_trajectories": int(len(per_traj)), "n_random": len(randoms) - (own is not None),
        }
    return out


def add_paired_vs_random(doc: dict[str, Any]) -> dict[str, Any]:
    """Store :func:`paired_vs_random` in each record as ``paired_vs_random`` (in place); returns ``doc``."""
    paired = paired_vs_random(doc)
    for rec in doc["records"]:
        if rec.get("policy") in paired:
            rec["paired_vs_random"] = paired[rec["policy"]]
    return doc


def rewrite_tables(folder: str | Path) -> Path:
    """Recompute ``paired_vs_random`` and ``placement.md`` of a finished run from its ``placement.json``
    (no filter runs): ``python -c "from dks_gym_agents.evaluate import rewrite_tables; rewrite_tables('DIR')"``."""
    folder = Path(folder)
    doc = add_paired_vs_random(load_results(folder / "placement.json"))
    save_results(doc, folder / "placement.json")
    (folder / "placement.md").write_text(ranked_table(doc))
    return folder / "placement.md"


# Table -------------------------------------------------------------------------------------------------
def _sci(x: float | None) -> str:
    return "-" if x is None or not math.isfinite(x) else f"{x:.2e}"


def _cost(x: float | None, scale: float = 1.0, unit: str = "") -> str:
    if x is None or not math.isfinite(x):
        return "-"
    v = x * scale
    return (f"{v:.3g}" if v >= 0.01 else f"{v:.1e}") + unit


def ranked_table(doc: dict[str, Any]) -> str:
    """Markdown: policies ranked by time-averaged MSE, with final MSE, paired ratio to the paper layout, costs."""
    recs = [r for r in doc["records"] if r["experiment"].startswith("placement/")]
    policies = sorted((r for r in recs if r["policy"] != "forward"), key=lambda r: r["time_mean_mse_mean"])
    paper = next((r for r in recs if r["policy"] == "paper"), None)
    forward = next((r for r in recs if r["policy"] == "forward"), None)
    paired = paired_vs_random(doc)
    head = ("| rank | policy | time-avg MSE (mean ± std) | final MSE (mean ± std) | time-avg / paper, paired "
            "(mean ± std) | better than paper | log(MSE / random mean), paired (mean ± s.e.) | "
            "better than random mean | offline cost | per decision |")
    lines = [head, "|" + "---|" * 10]

    def random_cells(rec: dict[str, Any]) -> tuple[str, str]:
        p = paired.get(rec["policy"])
        if p is None:
            return "-", "-"
        se = "-" if p["log_ratio_se"] is None else f"{p['log_ratio_se']:.3f}"
        return f"{p['log_ratio_mean']:+.3f} ± {se}", f"{p['wins']}/{p['n_episodes']}"

    def ratio_cells(rec: dict[str, Any]) -> tuple[str, str]:
        if paper is None:
            return "-", "-"
        a = np.asarray(rec["per_trajectory_time_mean_mse"], dtype=float)
        b = np.asarray(paper["per_trajectory_time_mean_mse"], dtype=float)
        q = a / b
        wins = int(np.sum(a < b))
        return f"{q.mean():.3f} ± {q.std(ddof=1) if len(q) > 1 else 0:.3f}", f"{wins}/{len(q)}"

    for i, rec in enumerate(policies, 1):
        kind = " (adaptive)" if rec.get("adaptive") else ""
        ratio, wins = ratio_cells(rec)
        lr, lw = random_cells(rec)
        lines.append(
            f"| {i} | {rec['policy']}{kind} | {_sci(rec['time_mean_mse_mean'])} ± {_sci(rec['time_mean_mse_std'])} | "
            f"{_sci(rec['final_mse_mean'])} ± {_sci(rec['final_mse_std'])} | {ratio} | {wins} | {lr} | {lw} | "
            f"{_cost(rec.get('offline_seconds'), 1, ' s')} | {_cost(rec.get('decision_seconds'), 1e3, ' ms')} |"
        )
    if forward is not None:
        ratio, wins = ratio_cells(forward)
        lr, lw = random_cells(forward)
        lines.append(f"| - | forward run (no sensors) | {_sci(forward['time_mean_mse_mean'])} ± "
                     f"{_sci(forward['time_mean_mse_std'])} | {_sci(forward['final_mse_mean'])} ± "
                     f"{_sci(forward['final_mse_std'])} | {ratio} | {wins} | {lr} | {lw} | - | - |")
    randoms = [r["time_mean_mse_mean"] for r in recs if r["policy"].startswith("random-")]
    cfg = doc["config"]
    notes = [
        "",
        f"{doc['benchmark']}, {cfg['model']} ({cfg['model_preset']}, r={cfg['r']}) with {cfg['filter']}, "
        f"m={cfg['n_sensors']}, noise level {cfg['noise_level']:g}; {cfg['n_episodes']} test episodes = "
        f"{cfg['n_test']} trajectories x {len(cfg['noise_seeds'])} noise seed(s) {cfg['noise_seeds']}, "
        f"{cfg['n_frames']} frames each. MSE in physical units over the scored channels; std = sample std "
        "across episodes (trajectory x noise seed: it mixes how hard the trajectories are with the noise); "
        "paired ratio = per-episode time-averaged MSE divided by the paper layout's on the "
        "same trajectory and noise. Paired vs random: per episode, log of the policy's time-averaged MSE over "
        "the mean of the random layouts' on the same episode (for a random-s row, the other seeds), mean ± "
        "standard error (std / sqrt(episodes)); negative = better than random; 'better than random mean' "
        "counts those episodes. Offline cost = fitting on the "
        "training split (incl. RL training, also when loaded from a checkpoint); per decision = one layout "
        "(static: per episode; adaptive: per step and trajectory).",
    ]
    if len(randoms) > 1:
        own = [p["log_ratio_mean"] for k, p in paired.items() if k.startswith("random-")]
        notes.append(f"Random layouts ({len(randoms)} seeds): time-averaged MSE {np.mean(randoms):.2e} ± "
                     f"{np.std(randoms, ddof=1):.2e} (mean ± std over seeds); their own paired log ratios "
                     f"against the other seeds' mean average {np.mean(own):+.3f} (the arithmetic mean is pulled "
                     "up by the worst layouts), the bar a policy must clear to beat a typical random layout; "
                     "placement.json also holds the log ratio against the geometric mean "
                     "(paired_vs_random.log_ratio_geometric_mean), for which that bar is 0.")
    return "\n".join(lines + notes) + "\n"


# Figure ------------------------------------------------------------------------------------------------
def layout_figure(task: PlacementTask, results: Sequence[PolicyResult], path: str | Path,
                  trajectory: int | None = None) -> Path:
    """Each policy's layout over the observed field of one test trajectory (default: median parameter) at the
    final frame. 1D: the field on top and one strip of sensor positions per policy; 2D/3D: one panel per
    policy (3D: the mid-plane z slice, off-plane sensors as +). Adaptive policies show the cells read at
    the final step."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    from matplotlib.figure import Figure

    from dks_gym.envs.render import draw_field

    ds, bench = task.dataset, task.benchmark
    split = task.config.split
    index = results[0].result.trajectories
    params = ds.params(split)[index]
    if trajectory is None:
        pos = int(np.argsort(params)[len(params) // 2])
    else:
        pos = int(np.flatnonzero(index == trajectory)[0])
    traj = int(index[pos])
    frame = ds.n_frames - 1
    field_ = ds.frame(split, traj, frame)[bench.observed_index]
    title = f"{bench.name}: {bench.observed_channel} at t={ds.time[frame]:.3g}, {ds.param_name}={params[pos]:.4g}"

    def cells_of(pr: PolicyResult) -> np.ndarray:
        return pr.layouts[pos, -1] if pr.policy.adaptive else pr.layouts[pos]

    if bench.ndim == 1:
        x = ds.coords[0]
        fig = Figure(figsize=(8, 2.2 + 0.28 * len(results)), dpi=120)
        top, strip = fig.subplots(2, 1, sharex=True, gridspec_kw={"height_ratios": [2.2, 0.28 * len(results) + 0.3]})
        top.plot(x, field_, lw=1.2, color="0.2")
        top.set_ylabel(bench.observed_channel)
        top.set_title(title, fontsize=9)
        for i, pr in enumerate(results):
            cells = cells_of(pr)
            strip.plot(x[cells], np.full(len(cells), i), "|" if not pr.policy.adaptive else "x", ms=9, mew=1.6,
                       color=f"C{i % 10}")
        strip.set_yticks(range(len(results)), [pr.name + (" (step)" if pr.policy.adaptive else "") for pr in results],
                         fontsize=7)
        strip.set_ylim(len(results) - 0.5, -0.5)
        strip.set_xlabel("x")
        strip.grid(axis="x", alpha=0.3)
    else:
        ncols = min(4, len(results))
        nrows = math.ceil(len(results) / ncols)
        fig = Figure(figsize=(4.2 * ncols, 3.2 * nrows), dpi=100)
        axes = np.atleast_1d(fig.subplots(nrows, ncols, squeeze=False)).ravel()
        vmax = float(np.abs(field_).max())
        for ax, pr in zip(axes, results):
            draw_field(ax, bench, ds.coords, field_, cells_of(pr), bench.fluid_mask(ds.cell_type),
                       pr.name + (" (last step)" if pr.policy.adaptive else ""), vmin=-vmax, vmax=vmax)
        for ax in axes[len(results):]:
            ax.set_visible(False)
        fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    return path


# Entry point -------------------------------------------------------------------------------------------
def evaluate_placement(
    benchmark: str,
    policies: Sequence[str | PlacementPolicy] | str = ("paper", "random", "qr", "greedy"),
    *,
    model: str = "koopman",
    filter: str = "ekf",
    model_preset: str = "lite",
    data_preset: str = "paper",
    n_sensors: int = 16,
    noise_level: float = 0.2,
    noise_seed: int = 0,
    noise_seeds: int = 1,
    faults: SensorFaults | dict[str, Any] | str | None = None,
    constraint: str | np.ndarray | None = None,
    random_seeds: int = 5,
    greedy_candidates: int | None = None,
    greedy_trajectories: int | None = None,
    sequential: str | Path | None = None,
    ppo: str | Path | None = None,
    agent_timesteps: int | None = None,
    out: str | Path | None = None,
    device: str = "cpu",
    train_if_missing: bool = False,
    task: PlacementTask | None = None,
    skip_unfit: bool = False,
    shred: Sequence[str] = (),
    shred_config: ShredConfig = ShredConfig(),
    log: Callable[[str], None] = print,
) -> tuple[dict[str, Any], list[PolicyResult]]:
    """Fit and run the named policies on BENCHMARK's test split; write JSON, table and figure to ``out``.

    Returns the results document and the per-policy results. Episodes: every test trajectory under the
    ``noise_seeds`` noise seeds ``noise_seed, noise_seed + 1, ...``. ``faults``: the sensors' faults in every
    episode (a :class:`~dks_gym.envs.SensorFaults`, a dict of its fields, or "default" for
    :data:`DEFAULT_FAULTS`); the policies are fitted without them. ``constraint``: where sensors may go
    (:func:`~dks_gym_agents.policies.constraint_candidates`: "fluid", "surface", a keep-out mask or the allowed
    cells; the paper layout moves to the nearest allowed cells). ``task`` replaces the dataset/model lookup
    (its config is used as is, its noise seed being the first). Learned policies ("sequential", "ppo") load
    the given checkpoints or train, saving their checkpoints and learning curves under ``out/agents``.
    ``skip_unfit``: leave out (and record in ``config.skipped_policies``) a policy that cannot be fitted, e.g.
    QR with more sensors than the data have POD modes, instead of stopping. ``shred``: names of static
    policies in the run whose layout a SHRED baseline is trained on and scored with (:func:`evaluate_shred`;
    ``shred_config`` its settings), each a ``shred-<policy>`` row.
    """
    start = time.perf_counter()
    if task is None:
        task = PlacementTask.load(benchmark, model, model_preset=model_preset, data_preset=data_preset, device=device,
                                  train_if_missing=train_if_missing, kind=filter, n_sensors=n_sensors,
                                  noise_level=noise_level, noise_seed=noise_seed)
    scenario = DEFAULT_FAULTS if faults == "default" else faults
    allowed = constraint_candidates(task.dataset, constraint)
    if allowed is not None:
        task = dataclasses.replace(task, candidates=allowed)
    out = Path(out) if out is not None else None
    chosen = make_policies(policies, random_seeds=random_seeds, greedy_candidates=greedy_candidates,
                           greedy_trajectories=greedy_trajectories, sequential=sequential, ppo=ppo,
                           agent_timesteps=agent_timesteps, agent_out=None if out is None else out / "agents")
    seeds = list(range(task.config.noise_seed, task.config.noise_seed + int(noise_seeds)))
    skipped: dict[str, str] = {}
    for policy in list(chosen):  # fitted on the training split without faults: a layout is chosen before it breaks
        if policy.task is None:
            try:
                policy.fit(task)
            except ValueError as exc:  # e.g. QR asked for more sensors than the data hold POD modes
                if not skip_unfit:
                    raise
                log(f"{policy.name:>14}: skipped at m = {task.n_sensors} ({exc})")
                skipped[policy.name] = str(exc)
                chosen.remove(policy)
    if not chosen:
        raise ValueError(f"no policy could be fitted at m = {task.n_sensors}: {skipped}")
    if scenario is not None:
        task = dataclasses.replace(task, config=task.config.replace(faults=scenario))
    results = []
    for policy in chosen:
        pr = evaluate_policy(task, policy, noise_seeds=seeds)
        log(f"{policy.name:>14}: fit {policy.fit_seconds:8.2f} s, time-avg MSE {pr.time_mean_mse.mean():.3e}, "
            f"final MSE {pr.result.final_mse_mean:.3e}")
        results.append(pr)
    index, episode_seeds = episodes(task, noise_seeds=seeds)
    static = next((pr.layouts for pr in results if not pr.policy.adaptive), None)
    forward = run_layouts(task.model, task.dataset, static if static is not None else
                          np.repeat(task.benchmark.paper_layout(task.n_sensors)[None], len(index), 0),
                          index, task.config.replace(kind="forward"), noise_seeds=episode_seeds)
    estimators = []
    for name in dict.fromkeys(shred):
        pr = next((pr for pr in results if pr.name == name), None)
        if pr is None:
            log(f"{'shred-' + name:>14}: skipped ({name!r} is not in this run)")
            skipped[f"shred-{name}"] = f"{name!r} is not in this run"
            continue
        rec = evaluate_shred(task, pr, seeds, shred_config, progress=True)
        log(f"{rec['policy']:>14}: fit {rec['fit_seconds']:8.2f} s, time-avg MSE {rec['time_mean_mse_mean']:.3e}, "
            f"final MSE {rec['final_mse_mean']:.3e} (POD floor {rec['pod_floor_time_mean_mse']:.1e})")
        estimators.append(rec)
    doc = placement_document(task, results, forward, model_preset=model_preset,
                             wall_time=time.perf_counter() - start)
    doc["records"].extend(estimators)
    doc = add_paired_vs_random(doc)
    doc["config"]["skipped_policies"] = skipped
    if out is not None:
        save_results(doc, out / "placement.json")
        (out / "placement.md").write_text(ranked_table(doc))
        layout_figure(task, results, out / "placement_layouts.png")
        log(f"wrote {out / 'placement.json'}, {out / 'placement.md'}, {out / 'placement_layouts.png'}")
    return doc, results


def evaluate_budgets(benchmark: str, policies: Sequence[str | PlacementPolicy] | str, budgets: Sequence[int], *,
                     out: str | Path, resume: bool = False, log: Callable[[str], None] = print,
                     **options: Any) -> dict[int, dict[str, Any]]:
    """:func:`evaluate_placement` at each sensor budget m in ``budgets`` (``out/m{m}``), then ``out/budgets.md``
    and ``out/budgets.png``: per policy and budget the time-averaged MSE and its paired log ratio to the random
    layouts of the same episodes, with the standard error over trajectories (the error-vs-budget curves with
    paired confidence bands). ``options`` go to :func:`evaluate_placement` (``faults``, ``model``, ...).
    Your own policy objects rank beside the named ones: each budget fits a fresh copy of an unfitted one (a
    fitted policy holds one budget's layout and is refused with several budgets).
    ``resume``: keep the budgets an earlier call with the same settings wrote to ``out`` (each budget's
    ``placement.json`` is written when that budget is done) instead of rerunning them, and show every budget
    in ``out`` in the table and figure: an interrupted sweep goes on where it stopped, a later call adds budgets.
    """
    budgets = sorted({int(m) for m in budgets})
    if not budgets or budgets[0] < 1:
        raise ValueError(f"budgets must be positive sensor counts, got {budgets!r}")
    if isinstance(policies, str):
        policies = [n.strip() for n in policies.split(",") if n.strip()]
    if len(budgets) > 1 and any(isinstance(p, PlacementPolicy) and p.task is not None for p in policies):
        raise ValueError("a fitted policy object holds one budget's layout; pass it unfitted (each budget fits a "
                         "copy) or by name to compare budgets")
    out = Path(out)
    kept = finished_budgets(out, benchmark, options) if resume else {}
    docs = {}
    task = options.pop("task", None)
    for m in budgets:
        if m in kept:
            log(f"budget m = {m}: kept {out / f'm{m}' / 'placement.json'}")
            continue
        log(f"budget m = {m}")
        if task is not None:  # a given task holds its own sensor count
            options["task"] = dataclasses.replace(task, config=task.config.replace(n_sensors=m))
        fresh = [copy.deepcopy(p) if isinstance(p, PlacementPolicy) else p for p in policies]
        docs[m], _ = evaluate_placement(benchmark, fresh, n_sensors=m, out=out / f"m{m}", log=log,
                                        skip_unfit=True, **options)
    docs = dict(sorted({**kept, **docs}.items()))
    if kept:
        same_settings(docs, out)
    (out / "budgets.md").write_text(budget_table(docs))
    budget_figure(docs, out / "budgets.png")
    log(f"wrote {out / 'budgets.md'}, {out / 'budgets.png'}")
    return docs


#: Config entries that may differ between the budgets of one sweep (the budget itself, when and how it ran).
_PER_RUN = ("n_sensors", "policies", "skipped_policies", "created", "wall_time_s", "dks_gym_version",
            "torch_version", "python")


def _policy_names(doc: dict[str, Any]) -> set[str]:
    """The policies a run was asked for: those it ran, the SHRED rows and those it skipped."""
    cfg = doc["config"]
    return (set(cfg["policies"]) | set(cfg.get("skipped_policies", {}))
            | {r["policy"] for r in doc["records"] if str(r.get("policy", "")).startswith("shred-")})


def same_settings(docs: dict[int, dict[str, Any]], out: Path) -> None:
    """Refuse budgets of ``out`` that were made with other settings than the first one (all but the budget)."""
    first_m = min(docs)
    first = docs[first_m]
    # as stored: a budget run now holds tuples (the faults' slow_sensors) where one read back holds lists
    stored = {m: json.loads(json.dumps(doc["config"])) for m, doc in docs.items()}
    for m, doc in docs.items():
        differ = sorted(k for k in set(stored[first_m]) | set(stored[m]) if k not in _PER_RUN
                        and stored[first_m].get(k) != stored[m].get(k))
        if doc["benchmark"] != first["benchmark"]:
            differ.insert(0, "benchmark")
        if _policy_names(doc) != _policy_names(first):
            differ.append("policies")
        if differ:
            raise ValueError(f"{out / f'm{m}'} was made with other settings than {out / f'm{first_m}'} "
                             f"({', '.join(differ)} differ); write to another --out or delete the stale budget")


def finished_budgets(out: Path, benchmark: str, options: dict[str, Any]) -> dict[int, dict[str, Any]]:
    """The budgets an earlier sweep finished in ``out`` (``m<m>/placement.json``), checked against each other and
    against this call's benchmark, model, filter, noise and faults."""
    docs = {int(p.parent.name[1:]): load_results(p) for p in out.glob("m*/placement.json")
            if p.parent.name[1:].isdigit()}
    if not docs:
        return {}
    same_settings(docs, out)
    doc = docs[min(docs)]
    cfg = doc["config"]
    asked = {"benchmark": (doc["benchmark"], benchmark),
             "model": (cfg["model"], options.get("model", "koopman")),
             "filter": (cfg["filter"], options.get("filter", "ekf")),
             "model_preset": (cfg["model_preset"], options.get("model_preset", "lite")),
             "noise_level": (cfg["noise_level"], options.get("noise_level", 0.2)),
             "noise_seeds": (len(cfg["noise_seeds"]), options.get("noise_seeds", 1)),
             "faults": (SensorFaults.from_any(cfg.get("faults")),
                        SensorFaults.from_any(DEFAULT_FAULTS if options.get("faults") == "default"
                                              else options.get("faults")))}
    if "task" not in options:  # a given task brings its own noise seed
        asked["noise_seed"] = (cfg["noise_seed"], options.get("noise_seed", 0))
    differ = [k for k, (was, now) in asked.items() if was != now]
    if differ:
        raise ValueError(f"{out} holds budgets {sorted(docs)} made with other settings ({', '.join(differ)} "
                         "differ); write to another --out, or leave out --resume to overwrite them")
    return docs


def _budget_rows(docs: dict[int, dict[str, Any]]) -> dict[str, dict[int, dict[str, Any]]]:
    rows: dict[str, dict[int, dict[str, Any]]] = {}
    for m, doc in docs.items():
        for rec in doc["records"]:
            name = rec.get("policy")
            if name is None or name.startswith("random-") and name != "random-0":
                continue
            rows.setdefault("random" if name == "random-0" else name, {})[m] = rec
    return rows


def describe_faults(faults: dict[str, Any] | None) -> str:
    """The fault settings that differ from none, as ``name value`` pairs ("none" without faults)."""
    scenario = SensorFaults.from_any(faults)
    return "none" if scenario is None else ", ".join(f"{k} {v}" for k, v in scenario.changed().items())


def budget_table(docs: dict[int, dict[str, Any]]) -> str:
    """The error-vs-budget table: per policy and m, time-averaged MSE and the paired log ratio to random ± se."""
    budgets = sorted(docs)
    first = docs[budgets[0]]
    cfg = first["config"]
    faults = cfg.get("faults")
    lines = [f"# Sensor budgets: {first['benchmark']}, {cfg['model']} {cfg['filter']}", "",
             f"Time-averaged MSE over frames 1..n_t-1 of the {cfg['n_episodes']} test episodes; in brackets the "
             "paired log ratio to the random layouts of the same episodes (negative: better than random) ± its "
             "standard error over trajectories. Random: the first seeded layout's MSE, the ratio of the mean of "
             f"the others. Faults: {describe_faults(faults)}.", "",
             "| policy | " + " | ".join(f"m = {m}" for m in budgets) + " |",
             "|---|" + "---|" * len(budgets)]
    skipped = {(name, m): reason for m, doc in docs.items()
               for name, reason in doc["config"].get("skipped_policies", {}).items()}
    rows = _budget_rows(docs)
    for name in dict.fromkeys([*rows, *(name for name, _ in skipped)]):
        per_m = rows.get(name, {})
        cells = []
        for m in budgets:
            rec = per_m.get(m)
            if rec is None:
                cells.append("skipped" if (name, m) in skipped else "-")
                continue
            text = _sci(rec.get("time_mean_mse_mean"))
            paired = rec.get("paired_vs_random")
            if paired:
                se = paired.get("log_ratio_se_trajectories")
                text += f" ({paired['log_ratio_mean']:+.2f}" + (f" ± {se:.2f})" if se is not None else ")")
            cells.append(text)
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    for (name, m), reason in sorted(skipped.items(), key=lambda item: item[0][1]):
        lines.append(f"\n{name} skipped at m = {m}: {reason}")
    return "\n".join(lines) + "\n"


def budget_figure(docs: dict[int, dict[str, Any]], path: str | Path) -> Path:
    """Error vs budget per policy: the paired log ratio to random with a band of ± 2 standard errors."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    from matplotlib.figure import Figure

    fig = Figure(figsize=(10, 4))
    ax_mse, ax_ratio = fig.subplots(1, 2)
    colors = matplotlib.rcParams["axes.prop_cycle"].by_key()["color"]
    for i, (name, per_m) in enumerate(_budget_rows(docs).items()):
        color = colors[i % len(colors)]  # one colour per policy in both panels
        ms = sorted(per_m)
        ax_mse.plot(ms, [per_m[m]["time_mean_mse_mean"] for m in ms], "o-", label=name, color=color)
        paired = [(m, per_m[m].get("paired_vs_random")) for m in ms]
        paired = [(m, p) for m, p in paired if p and p.get("log_ratio_se_trajectories") is not None]
        if paired and name != "random":
            x = np.array([m for m, _ in paired])
            mean = np.array([p["log_ratio_mean"] for _, p in paired])
            se = np.array([p["log_ratio_se_trajectories"] for _, p in paired])
            ax_ratio.plot(x, mean, "o-", label=name, color=color)
            ax_ratio.fill_between(x, mean - 2 * se, mean + 2 * se, alpha=0.15, color=color)
    for ax in (ax_mse, ax_ratio):
        ax.set_xscale("log", base=2)
        ax.set_xlabel("sensors m")
    ax_mse.set_yscale("log")
    ax_mse.set_ylabel("time-averaged MSE")
    ax_ratio.axhline(0.0, color="k", lw=0.8)
    ax_ratio.set_ylabel("log(MSE / random), paired, ± 2 se")
    ax_mse.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    return Path(path)
