"""Wrap DKS/Burgers-v0 with each latent model; print the final-time MSE of forward run, EKF and EnKF (test split)."""
import gymnasium as gym

import dks_gym  # noqa: F401  (registers the environments)
from dks_gym.wrappers import LatentFilter

print(f"{'model':8s} {'forward':>10s} {'EKF':>10s} {'EnKF':>10s}")
for model in ("koopman", "pdmd", "mlp", "xlstm"):
    row = []
    for filt in ("none", "ekf", "enkf"):
        # lite models train on first use (a few minutes on 2 CPU cores) and are cached in the data home
        env = LatentFilter(gym.make("DKS/Burgers-v0"), model=model, filter=filt, train_if_missing=True)
        finals = []
        for trajectory in range(env.unwrapped.dataset.n_trajectories("test")):
            env.reset(seed=0, options={"trajectory": trajectory})
            done = False
            while not done:
                _, _, terminated, truncated, info = env.step(None)
                done = terminated or truncated
            finals.append(info["mse"])
        row.append(sum(finals) / len(finals))
    print(f"{model:8s} " + " ".join(f"{e:10.3e}" for e in row))
