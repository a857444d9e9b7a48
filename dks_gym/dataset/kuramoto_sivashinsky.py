"""Kuramoto-Sivashinsky trajectories as a dataset folder in The Well's layout: a flow none of the four
benchmarks is, generated here and brought in the way any flow of The Well is (``dks-gym data import the-well``).

The trajectories come from :mod:`dks_gym.solvers.kuramoto_sivashinsky` on a domain of :data:`DATA_LENGTH` = 22
(nu over the solver's :data:`~dks_gym.solvers.kuramoto_sivashinsky.NU_RANGE` [0.5, 1], so L_eff = L / sqrt(nu)
from 22 to 31.1), stored on 64 points (solved on 128). L = 22 is the classic low-dimensional chaotic KS (an
inertial manifold of about 8 dimensions; Cvitanovic, Davidchack & Siminos 2010; the latent models of Linot &
Graham 2020): its fields are held to 0.05 % of their variance by 16 POD modes. Over the nu range the
solver's Lyapunov scan (docs/validation.md#kuramoto-sivashinsky) has chaotic runs at L_eff = 22, 26 and 30
and weakly chaotic, periodic or travelling-wave ones between, so the benchmark mixes both. The solver's
own default, L = 60 (robust chaos, 128 points), is not used here: from 32 trajectories of 100 frames the
lite models could not learn it (every EKF estimate worse than the field's variance;
docs/results/kuramoto-sivashinsky/README.md). As in The Well, the files group the trajectories by parameter value: each
viscosity nu gets ``per_value`` random initial conditions (default one: pDMD needs distinct parameter values, as
the four benchmarks have), and the test viscosities lie between training ones (unseen values inside the training
range, as the four benchmarks' test splits). The boundary is periodic in x.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ..solvers.kuramoto_sivashinsky import NU_RANGE, Trajectories, trajectories
from .the_well import WellFlow, write_the_well

#: The files' ``dataset_name``: the benchmark name the import gives the flow.
DATASET_NAME = "kuramoto_sivashinsky"
#: Domain length of the generated data (the module docstring says why 22).
DATA_LENGTH = 22.0


def split_values(n_train: int, n_test: int) -> tuple[np.ndarray, np.ndarray]:
    """``n_train`` training viscosities evenly spaced over :data:`NU_RANGE` (its ends included), and ``n_test``
    test viscosities, each the midpoint of two neighbouring training values, spread evenly over the gaps."""
    if n_train < 2 or not 1 <= n_test <= n_train - 1:
        raise ValueError(f"need at least 2 training viscosities and 1 to n_train - 1 test ones (one per gap), got "
                         f"n_train={n_train}, n_test={n_test}")
    train = np.linspace(*NU_RANGE, n_train)
    gaps = np.round(np.linspace(0, n_train - 2, n_test)).astype(int)
    return train, (train[gaps] + train[gaps + 1]) / 2


def write_well_folder(data: Trajectories, test: Sequence[int], out_dir: str | Path) -> dict[str, list[Path]]:
    """Write KS trajectories in The Well's layout under ``out_dir`` (``data/train``, ``data/test``, one file
    per viscosity): the trajectories whose indices ``test`` lists form the test split, the others train.
    One t0 field ``u``, the parameter ``nu``, ``dataset_name`` :data:`DATASET_NAME`, periodic in x."""
    test_rows = np.unique(np.asarray(test, dtype=np.int64))
    n = len(data.nu)
    if test_rows.size == 0 or test_rows.size == n or test_rows.min() < 0 or test_rows.max() >= n:
        raise ValueError(f"test must list some, not all, of the trajectory indices 0..{n - 1}, got {list(test)}")
    rows = {"train": np.setdiff1d(np.arange(n), test_rows), "test": test_rows}
    shared = set(data.nu[rows["train"]].tolist()) & set(data.nu[rows["test"]].tolist())
    if shared:
        raise ValueError(f"viscosities {sorted(shared)} are in both splits; The Well keeps one value per file and "
                         "each file in one split")
    return write_the_well(WellFlow(
        name=DATASET_NAME, channels=("u",), param_name="nu", time=data.time, coords=(data.x,),
        params={split: data.nu[r] for split, r in rows.items()},
        fields=lambda split, r: data.u[rows[split][r]][:, :, None], boundaries=(("x", "PERIODIC", "both"),),
    ), out_dir)


def generate_well_folder(out_dir: str | Path, *, n_train: int = 32, n_test: int = 12, per_value: int = 1,
                         n_t: int = 100, n_x: int = 64, L: float = DATA_LENGTH,
                         seed: int = 0) -> dict[str, list[Path]]:
    """Solve ``per_value`` KS trajectories at each of ``n_train`` training and ``n_test`` test viscosities
    (:func:`split_values`; ``n_t`` frames 0.5 apart on ``n_x`` points of the domain [0, ``L``), the initial
    conditions from ``seed``) and write them in The Well's layout under ``out_dir`` (:func:`write_well_folder`);
    return the files per split."""
    train, test = split_values(n_train, n_test)
    nu = np.repeat(np.concatenate([train, test]), per_value)
    data = trajectories(n_traj=len(nu), n_t=n_t, n_x=n_x, nu=nu, L=L, seed=seed)
    return write_well_folder(data, np.arange(len(train) * per_value, len(nu)), out_dir)


__all__ = ["DATASET_NAME", "DATA_LENGTH", "generate_well_folder", "split_values", "write_well_folder"]
