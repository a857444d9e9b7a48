"""Sensor placement as a Markov decision process, learned with PPO (stable-baselines3).

An episode places the m sensors one by one on a candidate set. The observation is which candidates hold a
sensor so far plus the fraction placed; the action is the next candidate (``Discrete(n_candidates)``; a
candidate already taken moves to the nearest free one, so a layout never repeats a cell). All rewards are
0 except the last: minus the filter's time-averaged assimilation MSE (frames 1..n_t-1) of the finished
layout on the episode's training trajectory, divided by the same error of the paper layout on that
trajectory and noise (so the paper layout scores -1 on every trajectory, and the reward's spread comes
from the layout, not from how hard the trajectory is; ``reference="forward"`` divides by the forward-run
error instead).

:class:`SequentialPlacementVecEnv` runs N episodes in lockstep and scores their N layouts with one batched
filter (:func:`~dks_gym_agents.scoring.run_layouts`), caching scores of layouts seen before.
:class:`SequentialLayout` is the resulting static policy: the trained agent's deterministic rollout.

Training script (defaults: 32 candidates, 16 parallel episodes, 16,384 steps = 1024 episodes, a few minutes
on one CPU core for the lite Burgers model)::

    python -m dks_gym_agents.sequential burgers --timesteps 16384 --out docs/results/placement/burgers/agents
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from .baselines import PaperLayout
from .policies import PlacementTask, StaticPolicy, candidate_lattice
from .rl import PortableAgent, learn_ppo, load_agent, offline_seconds, record_ppo_run, trainer_command
from .scoring import forward_reference, run_layouts


class LayoutScorer:
    """Normalized filter error of layouts on training trajectories, with a cache (the sequential MDP's reward).

    ``score(layouts (B, m), trajectories (B,))`` = time-averaged filter MSE / the reference's on the same
    trajectory, both over frames 1..n_t-1 of the training split with the task's filter settings and noise.
    ``reference``: "paper" (the paper layout with the same filter) or "forward" (no assimilation).
    """

    def __init__(self, task: PlacementTask, reference: str = "paper") -> None:
        if reference not in ("paper", "forward"):
            raise ValueError(f"reference must be 'paper' or 'forward', got {reference!r}")
        self.task = task
        self.reference = reference
        if reference == "forward":
            self.reference_mse = forward_reference(task.model, task.dataset, task.config)  # (n_train,)
        else:
            n = task.dataset.n_trajectories("train")
            paper = PaperLayout().fit(task).layout
            result = run_layouts(task.model, task.dataset, np.repeat(paper[None], n, 0), np.arange(n), task.config,
                                 split="train")
            self.reference_mse = result.step_mse[:, 1:].mean(axis=1)
        self.cache: dict[tuple, float] = {}
        self.filter_runs = 0

    def score(self, layouts: np.ndarray, trajectories: np.ndarray) -> np.ndarray:
        layouts = np.atleast_2d(np.asarray(layouts, dtype=np.int64))
        trajectories = np.asarray(trajectories, dtype=np.int64)
        keys = [(tuple(np.sort(row).tolist()), int(t)) for row, t in zip(layouts, trajectories)]
        first: dict[tuple, int] = {}
        for i, k in enumerate(keys):
            if k not in self.cache:
                first.setdefault(k, i)
        todo = list(first.values())
        if todo:
            result = run_layouts(self.task.model, self.task.dataset, layouts[todo], trajectories[todo],
                                 self.task.config, split="train")
            self.filter_runs += len(todo)
            for i, err in zip(todo, result.step_mse[:, 1:].mean(axis=1)):
                self.cache[keys[i]] = float(err / self.reference_mse[trajectories[i]])
        return np.array([self.cache[k] for k in keys])


class SequentialPlacementEnv(gym.Env):
    """One placement episode: m steps, each adding one candidate; reward at the end = minus the normalized error."""

    metadata = {"render_modes": []}

    def __init__(self, scorer: LayoutScorer, candidates: np.ndarray) -> None:
        self.scorer = scorer
        self.candidates = np.asarray(candidates, dtype=np.int64)
        self.n_sensors = scorer.task.n_sensors
        if self.n_sensors > len(self.candidates):
            raise ValueError(f"{self.n_sensors} sensors cannot be placed on {len(self.candidates)} candidates")
        n_c = len(self.candidates)
        self.observation_space = spaces.Box(0.0, 1.0, shape=(n_c + 1,), dtype=np.float32)
        self.action_space = spaces.Discrete(n_c)
        self.n_train = scorer.task.dataset.n_trajectories("train")
        self._placed: list[int] = []
        self.trajectory = 0

    def _obs(self) -> np.ndarray:
        obs = np.zeros(len(self.candidates) + 1, dtype=np.float32)
        obs[self._placed] = 1.0
        obs[-1] = len(self._placed) / self.n_sensors
        return obs

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        super().reset(seed=seed)
        self._placed = []
        options = options or {}
        self.trajectory = int(options.get("trajectory", self.np_random.integers(self.n_train)))
        return self._obs(), {"trajectory": self.trajectory}

    def place(self, action: int) -> bool:
        """Add candidate ``action`` (or the nearest free one); return whether the layout is complete."""
        if len(self._placed) >= self.n_sensors:
            raise RuntimeError("the layout is complete; call reset()")
        a = int(action)
        if not 0 <= a < len(self.candidates):
            raise ValueError(f"action must be a candidate index in [0, {len(self.candidates)}), got {action!r}")
        if a in self._placed:
            free = np.setdiff1d(np.arange(len(self.candidates)), self._placed)
            a = int(free[np.argmin(np.abs(free - a) * 2 + (free > a))])  # nearest, the lower one on ties
        self._placed.append(a)
        return len(self._placed) == self.n_sensors

    @property
    def layout(self) -> np.ndarray:
        """The cells placed so far (flat grid indices, in placement order)."""
        return self.candidates[self._placed]

    def step(self, action: int):
        done = self.place(action)
        reward = -float(self.scorer.score(self.layout[None], [self.trajectory])[0]) if done else 0.0
        info = {"layout": self.layout.copy(), "trajectory": self.trajectory} if done else {}
        return self._obs(), reward, done, False, info


def SequentialPlacementVecEnv(scorer: LayoutScorer, candidates: np.ndarray, n_envs: int = 16,  # noqa: N802
                              seed: int = 0):
    """N :class:`SequentialPlacementEnv` in lockstep as an SB3 ``VecEnv``; the N final layouts are scored at once."""
    from stable_baselines3.common.vec_env.base_vec_env import VecEnv

    class _VecEnv(VecEnv):
        def __init__(self) -> None:
            self.envs = [SequentialPlacementEnv(scorer, candidates) for _ in range(n_envs)]
            super().__init__(n_envs, self.envs[0].observation_space, self.envs[0].action_space)
            self._actions = None
            self._next_seed = seed

        def reset(self):
            seeds = [s if s is not None else self._next_seed + i for i, s in enumerate(self._seeds)]
            self._next_seed += n_envs
            self._reset_seeds()
            return np.stack([e.reset(seed=s)[0] for e, s in zip(self.envs, seeds)])

        def step_async(self, actions: np.ndarray) -> None:
            self._actions = np.asarray(actions).reshape(n_envs)

        def step_wait(self):
            done = np.array([e.place(a) for e, a in zip(self.envs, self._actions)])
            rewards = np.zeros(n_envs, dtype=np.float32)
            infos: list[dict[str, Any]] = [{} for _ in range(n_envs)]
            obs = np.stack([e._obs() for e in self.envs])
            if done.any():  # all episodes have m steps, so they end together
                layouts = np.stack([e.layout for e in self.envs])
                trajectories = np.array([e.trajectory for e in self.envs])
                rewards[:] = -scorer.score(layouts, trajectories)
                for i, e in enumerate(self.envs):
                    infos[i] = {"terminal_observation": obs[i], "TimeLimit.truncated": False,
                                "layout": layouts[i], "trajectory": int(trajectories[i])}
                obs = np.stack([e.reset()[0] for e in self.envs])
            return obs, rewards, done, infos

        def close(self) -> None:
            pass

        def get_attr(self, attr_name: str, indices=None) -> list:
            return [getattr(self.envs[i], attr_name) for i in self._get_indices(indices)]

        def set_attr(self, attr_name: str, value: Any, indices=None) -> None:
            for i in self._get_indices(indices):
                setattr(self.envs[i], attr_name, value)

        def env_method(self, method_name: str, *args: Any, indices=None, **kwargs: Any) -> list:
            return [getattr(self.envs[i], method_name)(*args, **kwargs) for i in self._get_indices(indices)]

        def env_is_wrapped(self, wrapper_class: type, indices=None) -> list[bool]:
            return [False for _ in self._get_indices(indices)]

    return _VecEnv()


def train_sequential(task: PlacementTask, *, timesteps: int = 16384, n_envs: int = 16,
                     n_candidates: int | None = None,
                     candidates: np.ndarray | None = None, seed: int = 0, out: str | Path | None = None,
                     reference: str = "paper", ppo_kwargs: dict[str, Any] | None = None,
                     progress: bool = False) -> tuple[Any, dict[str, Any]]:
    """Train PPO on the placement MDP; returns (agent, metadata with the learning curve and costs).

    With ``out``, writes ``OUT/sequential.zip`` + ``.json`` (checkpoint) and ``OUT/sequential_curve.png``.
    PPO defaults: one episode per env per rollout (n_steps = m), gamma = 1 (the only reward is the last),
    batch 64, 10 epochs, learning rate 3e-4, entropy bonus 0.01.
    """
    from stable_baselines3.common.vec_env import VecMonitor

    start = time.perf_counter()
    cands = candidate_lattice(task, n_candidates) if candidates is None else np.asarray(candidates, dtype=np.int64)
    PlacementTask(task.dataset, task.model, task.config, candidates=cands)  # validates them
    scorer = LayoutScorer(task, reference)
    venv = VecMonitor(SequentialPlacementVecEnv(scorer, cands, n_envs=n_envs, seed=seed))
    m = task.n_sensors
    kwargs = dict(n_steps=m, batch_size=64, n_epochs=10, gamma=1.0, gae_lambda=1.0, learning_rate=3e-4,
                  ent_coef=0.01, seed=seed, device="cpu", verbose=0)
    kwargs.update(ppo_kwargs or {})
    agent, curve = learn_ppo(venv, kwargs, timesteps, progress)
    wall = time.perf_counter() - start
    # Reference: the paper layout's normalized error on every training trajectory, with the same filter.
    n_train = task.dataset.n_trajectories("train")
    paper = PaperLayout().fit(task).layout
    paper_return = -float(scorer.score(np.repeat(paper[None], n_train, 0), np.arange(n_train)).mean())
    title = (f"sequential placement, {task.benchmark.name} ({task.model.kind} {task.config.filter.kind}, "
             f"m={m}, {len(cands)} candidates)")
    meta = record_ppo_run(agent, curve, task, kind="sequential", candidates=cands, ppo_kwargs=kwargs,
                          train_seconds=wall, paper_return=paper_return, out=out, title=title, n_envs=n_envs,
                          filter_runs=scorer.filter_runs, reward_reference=reference)
    return agent, meta


class SequentialLayout(PortableAgent, StaticPolicy):
    """The static layout of a PPO agent trained on the placement MDP (its deterministic rollout).

    ``checkpoint``: load a trained agent (``OUT/sequential.zip``); otherwise ``fit`` trains one with
    :func:`train_sequential` (``timesteps``, ``n_envs``, ``n_candidates``, ``seed``, ``out``); ``fit_seconds``
    is then the training cost.
    """

    name = "sequential"

    def __init__(self, checkpoint: str | Path | None = None, *, timesteps: int = 16384, n_envs: int = 16,
                 n_candidates: int | None = None, seed: int = 0, out: str | Path | None = None, agent: Any = None,
                 candidates: np.ndarray | None = None) -> None:
        super().__init__()
        self.checkpoint = checkpoint
        self.settings = dict(timesteps=timesteps, n_envs=n_envs, n_candidates=n_candidates, seed=seed, out=out)
        self.agent = agent
        self.candidates = None if candidates is None else np.asarray(candidates, dtype=np.int64)
        self.meta: dict[str, Any] = {}

    def choose(self, task: PlacementTask) -> np.ndarray:
        if self.agent is None:
            if self.checkpoint is not None:
                self.agent, self.meta = load_agent(self.checkpoint, task, "sequential")
                self.candidates = np.asarray(self.meta["candidates"], dtype=np.int64)
            else:
                self.agent, self.meta = train_sequential(task, **self.settings, candidates=self.candidates)
                self.candidates = np.asarray(self.meta["candidates"], dtype=np.int64)
        if self.candidates is None:
            raise ValueError("an agent passed directly needs its candidates= as well")
        env = SequentialPlacementEnv.__new__(SequentialPlacementEnv)  # rollout only: no scorer needed
        env.candidates, env.n_sensors, env._placed = self.candidates, task.n_sensors, []
        done = False
        while not done:
            action, _ = self.agent.predict(env._obs(), deterministic=True)
            done = env.place(int(action))
        return env.layout

    def save_agents_to(self, folder: Path) -> None:
        if self.settings["out"] is None:
            self.settings["out"] = folder

    @property
    def offline_seconds(self) -> float:
        return offline_seconds(self.fit_seconds, self.checkpoint, self.meta)

    def describe(self) -> dict[str, Any]:
        out = dict(super().describe(), checkpoint=None if self.checkpoint is None else str(self.checkpoint))
        for key in ("timesteps", "train_seconds", "filter_runs", "paper_layout_return"):
            if key in self.meta:
                out[key] = self.meta[key]
        return out


def main(argv: list[str] | None = None) -> None:
    """Command line: train the sequential placement agent and save checkpoint, metadata and learning curve."""

    @trainer_command("Train PPO to place BENCHMARK's sensors one by one (reward: minus the filter's normalized "
                     "error).", timesteps=16384, n_envs=16)
    def cli(task: PlacementTask, **settings: Any) -> str:
        agent, meta = train_sequential(task, **settings, progress=False)
        policy = SequentialLayout(agent=agent, candidates=np.asarray(meta["candidates"])).fit(task)
        curve = meta["learning_curve"]["mean_return"]
        return (f"trained {meta['timesteps']} steps in {meta['train_seconds']:.0f} s ({meta['filter_runs']} filter "
                f"runs); mean return first/last rollout {curve[0]:.3f} / {curve[-1]:.3f}; paper layout "
                f"{meta['paper_layout_return']:.3f}\nlayout: {sorted(policy.layout.tolist())}\nwrote {settings['out']}")

    cli.main(args=argv, standalone_mode=True)


if __name__ == "__main__":
    main()
