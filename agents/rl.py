"""stable-baselines3 plumbing shared by the learned placement policies: learning curves, figures, checkpoints.

A checkpoint is SB3's own ``NAME.zip`` (``PPO.save``) plus ``NAME.json`` with what the agent needs besides
its weights (benchmark, candidates, sensor count, reward scale, model and dataset identity, training
settings and the learning curve), so a loaded agent refuses a task it was not trained for.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import numpy as np

from dks_gym.evaluation.figures import save_figure


def _sb3():
    try:
        import stable_baselines3
    except ImportError as exc:  # pragma: no cover - depends on the install
        raise ImportError("the learned placement policies need stable-baselines3: "
                          "pip install 'dks-gym[agents]'") from exc
    return stable_baselines3


def learning_curve_callback():
    """A callback recording, after every rollout, the timesteps so far and the mean return of the episodes it ended."""
    from stable_baselines3.common.callbacks import BaseCallback

    class LearningCurve(BaseCallback):
        def __init__(self) -> None:
            super().__init__()
            self.timesteps: list[int] = []
            self.mean_return: list[float] = []
            self.episodes: list[int] = []
            self.wall: list[float] = []
            self._returns: list[float] = []
            self._start = time.perf_counter()

        def _on_step(self) -> bool:
            for info in self.locals.get("infos", []):
                if "episode" in info:
                    self._returns.append(float(info["episode"]["r"]))
            return True

        def _on_rollout_end(self) -> None:
            if self._returns:
                self.timesteps.append(int(self.num_timesteps))
                self.mean_return.append(float(np.mean(self._returns)))
                self.episodes.append(len(self._returns))
                self.wall.append(time.perf_counter() - self._start)
                self._returns = []

        def as_dict(self) -> dict[str, list]:
            return {"timesteps": self.timesteps, "mean_return": self.mean_return, "episodes": self.episodes,
                    "wall_s": self.wall}

    return LearningCurve()


def quiet_logger():
    """An SB3 logger with no outputs (the default one creates an empty SB3-* folder in the temp dir per run)."""
    from stable_baselines3.common.logger import Logger

    return Logger(folder=None, output_formats=[])


def save_learning_curve(curve: dict[str, list], path: str | Path, title: str,
                        references: dict[str, float] | None = None) -> Path:
    """Plot mean episode return against timesteps, with horizontal lines for reference layouts; write PNG."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    from matplotlib.figure import Figure

    fig = Figure(figsize=(6, 3.6), dpi=110)
    ax = fig.subplots()
    ax.plot(curve["timesteps"], curve["mean_return"], "o-", ms=3, lw=1.2, label="PPO (mean return per rollout)")
    for i, (name, value) in enumerate((references or {}).items()):
        ax.axhline(value, ls="--", lw=1, color=f"C{i + 1}", label=name)
    ax.set_xlabel("environment steps")
    ax.set_ylabel("mean episode return")
    ax.set_title(title, fontsize=9)
    ax.legend(fontsize=7)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    return save_figure(fig, path, dpi=fig.dpi, tight=False)


def learn_ppo(env: Any, ppo_kwargs: dict[str, Any], timesteps: int, progress: bool) -> tuple[Any, Any]:
    """Train an SB3 ``PPO("MlpPolicy")`` on ``env`` quietly; return (agent, its learning-curve callback)."""
    PPO = _sb3().PPO
    agent = PPO("MlpPolicy", env, **ppo_kwargs)
    agent.set_logger(quiet_logger())
    curve = learning_curve_callback()
    agent.learn(total_timesteps=int(timesteps), callback=curve, progress_bar=progress)
    return agent, curve


def record_ppo_run(agent: Any, curve: Any, task: Any, *, kind: str, candidates: np.ndarray, ppo_kwargs: dict[str, Any],
                   train_seconds: float, paper_return: float, out: str | Path | None, title: str,
                   **extra: Any) -> dict[str, Any]:
    """The metadata of a trained placement agent (``extra`` adds to it); with ``out``, also write
    ``OUT/KIND.zip`` + ``.json`` and ``OUT/KIND_curve.png`` with the paper layout's return as a dashed line."""
    meta = {
        "kind": kind, "identity": model_identity(task), "candidates": np.asarray(candidates).tolist(),
        "timesteps": int(agent.num_timesteps), "seed": ppo_kwargs.get("seed"),
        "ppo": {k: v for k, v in ppo_kwargs.items() if k not in ("device", "verbose")},
        "train_seconds": train_seconds, **extra,
        "learning_curve": curve.as_dict(), "paper_layout_return": paper_return,
    }
    if out is not None:
        out = Path(out)
        save_agent(agent, out / f"{kind}.zip", meta)
        save_learning_curve(curve.as_dict(), out / f"{kind}_curve.png", title,
                            {"paper layout (all training trajectories)": paper_return})
    return meta


def model_identity(task: Any) -> dict[str, Any]:
    """What a learned policy was trained with: benchmark, latent model, dataset fingerprint, filter settings."""
    from dks_gym.evaluation.results import shared_dataset
    from dks_gym.models.checkpoint import dataset_identity

    return {"benchmark": task.benchmark.name, "model": task.model.kind, "r": int(task.model.r),
            "n_sensors": task.n_sensors, "dataset": shared_dataset(dataset_identity(task.dataset)),
            "config": task.config.as_record()}


def save_agent(agent: Any, path: str | Path, metadata: dict[str, Any]) -> Path:
    """Write ``path`` (.zip, SB3) and its ``.json`` metadata; returns the .zip path."""
    path = Path(path).with_suffix(".zip")
    path.parent.mkdir(parents=True, exist_ok=True)
    agent.save(path)
    path.with_suffix(".json").write_text(json.dumps(metadata, indent=1, default=_plain) + "\n")
    return path


def load_agent(path: str | Path, task: Any, kind: str, device: str = "cpu") -> tuple[Any, dict[str, Any]]:
    """Load a PPO agent and its metadata; raise if it was trained for another kind, benchmark or sensor count."""
    sb3 = _sb3()
    path = Path(path).with_suffix(".zip")
    meta_path = path.with_suffix(".json")
    if not path.exists() or not meta_path.exists():
        raise FileNotFoundError(f"no agent checkpoint at {path} (with {meta_path.name}); train one first "
                                f"(python -m dks_gym_agents.{kind} BENCHMARK --out DIR)")
    meta = json.loads(meta_path.read_text())
    if meta.get("kind") != kind:
        raise ValueError(f"{path} holds a {meta.get('kind')!r} agent, not a {kind!r} one")
    ident = meta.get("identity", {})
    for key, want in (("benchmark", task.benchmark.name), ("n_sensors", task.n_sensors), ("r", int(task.model.r))):
        if ident.get(key) != want:
            raise ValueError(f"{path} was trained with {key}={ident.get(key)!r}, but the task has {key}={want!r}")
    return sb3.PPO.load(path, device=device), meta


class PortableAgent:
    """Mixin of the learned policies (their SB3 agent in ``self.agent``): pickled, e.g. to a worker of
    :func:`dks_gym.parallel.map_tasks` and back, the agent travels as the bytes of its own checkpoint format
    (``PPO.save``, the weights and settings, not the training environment, which cannot be pickled)."""

    def __getstate__(self) -> dict[str, Any]:
        import io

        state = self.__dict__.copy()
        if state.get("agent") is not None:
            buffer = io.BytesIO()
            state["agent"].save(buffer)
            state["agent"] = (buffer.getvalue(), str(state["agent"].device))
        return state

    def __setstate__(self, state: dict[str, Any]) -> None:
        import io

        if isinstance(state.get("agent"), tuple):
            data, device = state["agent"]
            state["agent"] = _sb3().PPO.load(io.BytesIO(data), device=device)
        self.__dict__.update(state)


def _plain(obj: Any) -> Any:
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, (np.integer, np.floating)):
        return obj.item()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"cannot store {type(obj).__name__} in agent metadata")


def trainer_command(help_text: str, timesteps: int, n_envs: int):
    """A click command with the options both agent trainers share; the decorated function gets the loaded
    ``PlacementTask`` and the training settings (timesteps, n_envs, n_candidates, seed, out).
    ``--train-if-missing`` trains the latent model first when its checkpoint is missing (lite: about a
    minute on one core for Burgers); without it a missing checkpoint is a clear error."""
    import click

    def wrap(train: Any) -> Any:
        @click.command(help=help_text)
        @click.argument("benchmark")
        @click.option("--model", default="koopman", show_default=True)
        @click.option("--filter", "filter_", default="ekf", show_default=True)
        @click.option("--preset", default="lite", show_default=True, help="Latent model preset.")
        @click.option("--data-preset", default="paper", show_default=True)
        @click.option("--timesteps", type=int, default=timesteps, show_default=True)
        @click.option("--n-envs", type=int, default=n_envs, show_default=True)
        @click.option("--n-candidates", type=int, default=32, show_default=True)
        @click.option("--n-sensors", type=int, default=16, show_default=True)
        @click.option("--seed", type=int, default=0, show_default=True)
        @click.option("--train-if-missing", is_flag=True,
                      help="Train the latent model (PRESET on DATA_PRESET) when its checkpoint is missing.")
        @click.option("--out", type=click.Path(file_okay=False, path_type=Path), required=True)
        def command(benchmark: str, model: str, filter_: str, preset: str, data_preset: str, timesteps: int,
                    n_envs: int, n_candidates: int, n_sensors: int, seed: int, train_if_missing: bool,
                    out: Path) -> None:
            from dks_gym.models.checkpoint import CheckpointMissing

            from .policies import PlacementTask

            try:
                task = PlacementTask.load(benchmark, model, model_preset=preset, data_preset=data_preset,
                                          kind=filter_, n_sensors=n_sensors, seed=seed,
                                          train_if_missing=train_if_missing)
            except CheckpointMissing as exc:
                raise click.ClickException(f"{exc} (pass --train-if-missing to train it here)") from exc
            click.echo(train(task, timesteps=timesteps, n_envs=n_envs, n_candidates=n_candidates, seed=seed,
                             out=out))

        return command

    return wrap


def offline_seconds(fit_seconds: float, checkpoint: Any, meta: dict[str, Any]) -> float:
    """Fitting time plus, for an agent loaded from a checkpoint, the training time recorded with it."""
    loaded = checkpoint is not None and "train_seconds" in meta
    return fit_seconds + (float(meta["train_seconds"]) if loaded else 0.0)

