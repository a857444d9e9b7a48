"""Adaptive sensing learned with PPO: a layout per step from the filter's belief (``sensor_mode="select"``).

The environment is the package's batched :class:`~dks_gym.wrappers.LatentFilterVectorEnv` on the *training*
split in select mode over a candidate set, adapted to stable-baselines3 by
:func:`~dks_gym.wrappers.SB3VecEnv`. Observation: the filter's belief ``[latent mean (r); log diag P (r)]``;
action: m candidate indices (``MultiDiscrete([n_candidates] * m)``; repeated picks move to the nearest free
candidate, as in :meth:`~dks_gym_agents.policies.AdaptivePolicy.decide`, so training and evaluation read the same
cells); reward: minus the reconstruction MSE of the step divided by the mean forward-run MSE of the training
trajectories (about -1 per step for a filter no better than the open-loop model).

Training script (defaults: 32 candidates, 8 environments, 20,480 steps, about 2-4 minutes on one CPU core for
the lite Burgers model)::

    python -m dks_gym_agents.adaptive burgers --timesteps 20480 --out docs/results/placement/burgers/agents
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path
from typing import Any

import numpy as np

from .baselines import PaperLayout
from .policies import AdaptivePolicy, PlacementTask, candidate_lattice, distinct_picks
from .rl import PortableAgent, learn_ppo, load_agent, offline_seconds, record_ppo_run, trainer_command
from .scoring import forward_reference, run_layouts


def make_adaptive_env(task: PlacementTask, candidates: np.ndarray, *, n_envs: int = 8, seed: int = 0,
                      reward_scale: float = 1.0):
    """The SB3 training environment: N select-mode filter envs on the training split, distinct picks, scaled reward."""
    from stable_baselines3.common.vec_env import VecEnvWrapper, VecMonitor

    from dks_gym.wrappers import LatentFilterVectorEnv, SB3VecEnv

    venv = LatentFilterVectorEnv(
        task.benchmark.name, n_envs, model=task.model,
        config=dataclasses.replace(task.config.filter, on_divergence="reset", seed=seed),
        preset=task.dataset.preset or "paper",
        data_path=str(task.dataset.path), split="train", sensor_mode="select", candidates=candidates,
        n_sensors=task.n_sensors, noise_level=task.config.noise_level,
        uncertainty=False,  # the reward is the MSE: the predictive std would cost r decoder passes per step
    )
    n_candidates = len(candidates)

    class DistinctScaled(VecEnvWrapper):
        """Moves repeated picks to free candidates and multiplies rewards by ``reward_scale``."""

        def step_async(self, actions: np.ndarray) -> None:
            self.venv.step_async(distinct_picks(np.asarray(actions), n_candidates))

        def step_wait(self):
            obs, rewards, dones, infos = self.venv.step_wait()
            return obs, (rewards * reward_scale).astype(np.float32), dones, infos

        def reset(self):
            return self.venv.reset()

    env = SB3VecEnv(venv)
    env.seed(seed)
    return VecMonitor(DistinctScaled(env))


def train_adaptive(task: PlacementTask, *, timesteps: int = 20480, n_envs: int = 8,
                   n_candidates: int | None = None,
                   candidates: np.ndarray | None = None, seed: int = 0, out: str | Path | None = None,
                   ppo_kwargs: dict[str, Any] | None = None, progress: bool = False) -> tuple[Any, dict[str, Any]]:
    """Train PPO for adaptive sensing; returns (agent, metadata with the learning curve and costs).

    With ``out``, writes ``OUT/adaptive.zip`` + ``.json`` (checkpoint) and ``OUT/adaptive_curve.png``, where
    the dashed line is the paper layout's mean return on the training trajectories with the same filter.
    PPO defaults: n_steps 128 per env, batch 256, 5 epochs, learning rate 3e-4, gamma 0.99.
    """
    start = time.perf_counter()
    cands = candidate_lattice(task, n_candidates) if candidates is None else np.asarray(candidates, dtype=np.int64)
    PlacementTask(task.dataset, task.model, task.config, candidates=cands)  # validates them
    forward = forward_reference(task.model, task.dataset, task.config)
    reward_scale = 1.0 / float(forward.mean())
    env = make_adaptive_env(task, cands, n_envs=n_envs, seed=seed, reward_scale=reward_scale)
    kwargs = dict(n_steps=128, batch_size=256, n_epochs=5, learning_rate=3e-4, gamma=0.99, seed=seed,
                  device="cpu", verbose=0)
    kwargs.update(ppo_kwargs or {})
    agent, curve = learn_ppo(env, kwargs, timesteps, progress)
    wall = time.perf_counter() - start
    # Reference: the paper layout's episode return on every training trajectory with the same filter.
    n_train = task.dataset.n_trajectories("train")
    paper = run_layouts(task.model, task.dataset, np.repeat(PaperLayout().fit(task).layout[None], n_train, 0),
                        np.arange(n_train), task.config, split="train")
    paper_return = -float(paper.step_mse[:, 1:].sum(axis=1).mean() * reward_scale)
    title = (f"adaptive sensing (PPO), {task.benchmark.name} ({task.model.kind} {task.config.filter.kind}, "
             f"m={task.n_sensors}, {len(cands)} candidates)")
    meta = record_ppo_run(agent, curve, task, kind="adaptive", candidates=cands, ppo_kwargs=kwargs, train_seconds=wall,
                          paper_return=paper_return, out=out, title=title, n_envs=n_envs, reward_scale=reward_scale)
    return agent, meta


class PPOAdaptive(PortableAgent, AdaptivePolicy):
    """A PPO agent choosing m of the candidates at every step from the filter's belief.

    ``checkpoint``: load a trained agent (``OUT/adaptive.zip``); otherwise ``fit`` trains one with
    :func:`train_adaptive` (``timesteps``, ``n_envs``, ``n_candidates``, ``seed``, ``out``), and
    ``fit_seconds`` is the training cost. Decisions are the agent's deterministic (most likely) actions.
    """

    name = "ppo"

    def __init__(self, checkpoint: str | Path | None = None, *, timesteps: int = 20480, n_envs: int = 8,
                 n_candidates: int | None = None, seed: int = 0, out: str | Path | None = None, agent: Any = None,
                 candidates: np.ndarray | None = None) -> None:
        super().__init__(candidates)
        self.checkpoint = checkpoint
        self.settings = dict(timesteps=timesteps, n_envs=n_envs, n_candidates=n_candidates, seed=seed, out=out)
        self.agent = agent
        self.meta: dict[str, Any] = {}

    def _fit(self, task: PlacementTask) -> None:
        if self.agent is None and self.checkpoint is not None:
            self.agent, self.meta = load_agent(self.checkpoint, task, "adaptive")
            self.candidates = np.asarray(self.meta["candidates"], dtype=np.int64)
        elif self.candidates is None:
            self.candidates = candidate_lattice(task, self.settings["n_candidates"])
        super()._fit(task)

    def train(self, task: PlacementTask) -> None:
        if self.agent is None:
            self.agent, self.meta = train_adaptive(task, **self.settings, candidates=self.candidates)

    def act(self, belief: np.ndarray) -> np.ndarray:
        action, _ = self.agent.predict(np.asarray(belief, dtype=np.float32), deterministic=True)
        return np.atleast_2d(action)

    def save_agents_to(self, folder: Path) -> None:
        if self.settings["out"] is None:
            self.settings["out"] = folder

    @property
    def offline_seconds(self) -> float:
        return offline_seconds(self.fit_seconds, self.checkpoint, self.meta)

    def describe(self) -> dict[str, Any]:
        out = dict(super().describe(), checkpoint=None if self.checkpoint is None else str(self.checkpoint),
                   n_candidates=None if self.candidates is None else len(self.candidates))
        for key in ("timesteps", "train_seconds", "paper_layout_return", "reward_scale"):
            if key in self.meta:
                out[key] = self.meta[key]
        return out


def main(argv: list[str] | None = None) -> None:
    """Command line: train the adaptive PPO agent and save checkpoint, metadata and learning curve."""

    @trainer_command("Train PPO to choose BENCHMARK's sensors at every step from the filter's belief.",
                     timesteps=20480, n_envs=8)
    def cli(task: PlacementTask, **settings: Any) -> str:
        _, meta = train_adaptive(task, **settings)
        curve = meta["learning_curve"]["mean_return"]
        first, last = (curve[0], curve[-1]) if curve else (float("nan"), float("nan"))
        return (f"trained {meta['timesteps']} steps in {meta['train_seconds']:.0f} s; "
                f"mean episode return first/last rollout {first:.2f} / {last:.2f}; "
                f"paper layout {meta['paper_layout_return']:.2f}\nwrote {settings['out']}")

    cli.main(args=argv, standalone_mode=True)


if __name__ == "__main__":
    main()
