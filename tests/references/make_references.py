"""Reference numbers of the cross-checks against ezyrb and PySensors, computed once with those packages.

tests/test_pdmd.py checks dks-gym's multiquadric RBF interpolant and its pDMD against ezyrb's ``RBF`` and
``POD`` (through PyDMD's ``ParametricDMD``); tests/test_agents.py checks its QR / CCQR sensor pivoting
against PySensors' ``SSPOR`` with its ``QR`` and ``CCQR`` optimizers. Neither package is installed by the
extras (ezyrb pulls Hugging Face ``datasets`` and pyarrow, python-sensors 184 MB of example data), so this
script computes what those tests compare with, from exactly the inputs the tests build (it imports their
helpers), and stores it in ``cross_checks.npz`` beside it, with the package versions. The tests read that
file; each also checks that its own inputs match the ones recorded here (:func:`assert_same_input`).

Regenerate from the repository root, in an environment with dks-gym's ``all`` and ``dev`` extras::

    pip install ezyrb==1.3.3 python-sensors==0.4.3
    OMP_NUM_THREADS=1 python tests/references/make_references.py

(the versions that computed the stored file; they are recorded in it under ``versions``).
"""

from __future__ import annotations

import functools
import json
import os
import sys
import tempfile
import warnings
from importlib import metadata
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
REFERENCES = HERE / "cross_checks.npz"
PACKAGES = ("ezyrb", "python-sensors", "pydmd", "numpy", "scipy", "scikit-learn")


# Shared with the tests -----------------------------------------------------------------------------------
def fingerprint(x: np.ndarray) -> np.ndarray:
    """A round-off-tolerant summary of an input array: its 2-norm and its normalized projection on a fixed
    pseudo-random vector (both change when the input drifts; a checksum of the bytes would change with the
    last bit of a BLAS or libm result)."""
    x = np.asarray(x, dtype=np.float64).ravel()
    norm = float(np.linalg.norm(x))
    w = np.random.default_rng(20240531).standard_normal(x.size)
    return np.array([norm, float(x @ w) / norm if norm > 0 else 0.0])


def input_entries(key: str, x: np.ndarray) -> dict[str, np.ndarray]:
    """What the reference file records of an input: ``<key>.shape`` and ``<key>.fingerprint``."""
    return {f"{key}.shape": np.array(np.shape(x), dtype=np.int64), f"{key}.fingerprint": fingerprint(x)}


def assert_same_input(refs: dict[str, np.ndarray], key: str, x: np.ndarray) -> None:
    """Raise if ``x`` is not (to round-off) the input the references were computed from."""
    np.testing.assert_array_equal(np.shape(x), refs[f"{key}.shape"], err_msg=f"{key}: shape drifted")
    stored = refs[f"{key}.fingerprint"]
    ours = fingerprint(x)
    np.testing.assert_allclose(ours[0], stored[0], rtol=1e-6, err_msg=f"{key}: input drifted (norm)")
    np.testing.assert_allclose(ours[1], stored[1], rtol=0, atol=1e-6, err_msg=f"{key}: input drifted (projection)")


@functools.lru_cache(maxsize=1)
def _load() -> dict[str, np.ndarray]:
    with np.load(REFERENCES, allow_pickle=False) as f:
        return {name: f[name] for name in f.files}


def load_references() -> dict[str, np.ndarray]:
    """The stored reference numbers, by key (a copy of the dict: the arrays are shared, do not modify them)."""
    return dict(_load())


def versions(refs: dict[str, np.ndarray]) -> dict[str, str]:
    """The package versions that computed ``refs``."""
    return json.loads(str(refs["versions"]))


# Computing them ------------------------------------------------------------------------------------------
def pdmd_references() -> dict[str, np.ndarray]:
    """tests/test_pdmd.py: ParametricDMD with ezyrb's POD and RBF on the dense data; ezyrb's RBF alone on
    the RBF cases; ParametricDMD with ezyrb's RBF on the POD coefficients of dks-gym's fit."""
    import ezyrb
    from pydmd import DMD, ParametricDMD

    from dks_gym.models.pdmd import _ReducedCoordinates
    from tests.test_pdmd import RBF_CASES, TEST_MU, TRAIN_MU, fitted, rbf_values

    out: dict[str, np.ndarray] = {}

    # test_matches_parametric_dmd_with_ezyrb_pod_on_dense_data: the reconstruction is modes x coefficients.
    _, data = fitted(r=6, mu_dependent_decay=True)
    out.update(input_entries("pdmd_dense.input", data))
    normalized = (data[:, :, 0].astype(np.float64) - 0.5) / 0.8  # (n, n_t, N)
    reference = ParametricDMD(DMD(svd_rank=6), ezyrb.POD("svd", rank=6), ezyrb.RBF(kernel="multiquadric"))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        reference.fit(normalized.transpose(0, 2, 1), TRAIN_MU)
    reference.parameters = TEST_MU
    full = np.real(reference.reconstructed_data)  # (n_test, N, n_t), normalized units
    modes = np.asarray(reference._spatial_pod.modes)  # (N, 6), real
    modal = np.real(reference.interpolated_modal_coefficients)  # (n_test, 6, n_t)
    compact = np.einsum("nr,prt->pnt", modes, modal)
    assert np.isrealobj(modes) and np.linalg.norm(compact - full) <= 1e-13 * np.linalg.norm(full)
    out["pdmd_dense.modes"], out["pdmd_dense.coefficients"] = modes, modal

    # test_multiquadric_rbf_equals_ezyrb_rbf: ezyrb's predictions and the scipy interpolator it builds
    for case, (points, new_points) in RBF_CASES.items():
        key = f"rbf.{case}"
        out[f"{key}.points"], out[f"{key}.new_points"] = points, new_points
        for name, y in rbf_values(points).items():
            rbf = ezyrb.RBF(kernel="multiquadric")
            rbf.fit(points, y)
            out[f"{key}.{name}.values"] = y
            out[f"{key}.{name}.epsilon"] = np.float64(rbf.epsilon)
            out[f"{key}.{name}.prediction"] = rbf.predict(new_points)
        scipy_rbf = rbf.interpolator  # a scipy.interpolate.RBFInterpolator: the call ezyrb makes
        out[f"{key}.scipy.kernel"] = np.array(scipy_rbf.kernel)
        out[f"{key}.scipy.epsilon"] = np.float64(scipy_rbf.epsilon)
        out[f"{key}.scipy.smoothing"] = np.asarray(scipy_rbf.smoothing, dtype=np.float64)
        out[f"{key}.scipy.powers"] = np.asarray(scipy_rbf.powers)
        out[f"{key}.scipy.neighbors"] = np.int64(-1 if scipy_rbf.neighbors is None else scipy_rbf.neighbors)

    # test_pdmd_online_operator_equals_the_one_with_ezyrb_rbf: ParametricDMD with ezyrb's RBF on the POD
    # coefficients of dks-gym's fit, unregularized (as the paper) and with dks-gym's default regularization
    # handed to PyDMD and ezyrb in absolute units: DMD(tikhonov_regularization=t), RBF(smooth=s).
    reference, _ = fitted(r=6, mu_dependent_decay=True)
    coeffs = reference.train_coefficients.numpy()  # (n_train, n_t, r)
    stacked = np.ascontiguousarray(coeffs.transpose(0, 2, 1))  # (n_train, r, n_t), as ParametricDMD takes them
    params = reference.train_params.numpy()
    mu = np.r_[TEST_MU, TRAIN_MU[[0, 7]], 0.005]
    out["pdmd_operator.train_coefficients"] = coeffs
    out["pdmd_operator.train_params"] = params
    out["pdmd_operator.mu"] = mu
    settings = reference.settings
    out["pdmd_operator.settings"] = np.array(json.dumps(settings, sort_keys=True))
    # PyDMD's Tikhonov term t acts as s -> (s^2 + t ||X||_F) / s: t = (dmd_tikhonov s_max)^2 / ||X||_F
    x = stacked[:, :, :-1].reshape(-1, stacked.shape[2] - 1)
    tikhonov = (settings["dmd_tikhonov"] * np.linalg.norm(x, 2)) ** 2 / np.linalg.norm(x)
    # scipy's smoothing: rbf_smoothing x the spectral norm of the doubly centered multiquadric kernel matrix
    epsilon = np.ptp(params)  # ezyrb's shape parameter for one parameter
    kernel = np.sqrt(1.0 + (epsilon * (params[:, None] - params[None, :])) ** 2)
    centering = np.eye(len(params)) - 1.0 / len(params)
    smoothing = settings["rbf_smoothing"] * np.linalg.norm(centering @ kernel @ centering, 2)
    for variant, dmd_kwargs, smooth in (("unregularized", {}, 0.0),
                                        ("regularized", {"tikhonov_regularization": tikhonov}, smoothing)):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)
            pdmd = ParametricDMD(DMD(svd_rank=6, **dmd_kwargs), _ReducedCoordinates(),
                                 ezyrb.RBF(kernel="multiquadric", smooth=smooth))
            pdmd.fit(stacked, params)
        reference._pdmd = pdmd
        reference._operator_cache.clear()
        out[f"pdmd_operator.{variant}.coefficients"] = reference.interpolated_coefficients(mu)
        out[f"pdmd_operator.{variant}.operator"] = reference.online_operator(mu).numpy()
    return out


def agents_references(workdir: Path) -> dict[str, np.ndarray]:
    """tests/test_agents.py: PySensors' SSPOR on the Burgers `small` data and the noisy cylinder file, and
    its QR / CCQR optimizers on the random bases."""
    import pysensors as ps

    from dks_gym.dataset import Dataset, generate_dataset
    from dks_gym_agents.baselines import observed_snapshots
    from tests.test_agents import PIVOT_CASES, _burgers_snapshots, _noisy_synthetic, _pivot_case

    out: dict[str, np.ndarray] = {}

    # test_qr_equals_pysensors_on_an_independent_svd_basis: the session's Burgers `small` preset.
    os.environ["DKS_GYM_HOME"] = str(workdir / "home")
    with Dataset(generate_dataset("burgers", "small", progress=False)) as ds:
        X = _burgers_snapshots(ds)
    out.update(input_entries("qr_burgers.input", X))
    reference = ps.SSPOR(basis=ps.basis.SVD(n_basis_modes=16, algorithm="arpack", random_state=0), n_sensors=16)
    out["qr_burgers.sensors"] = reference.fit(X, quiet=True).get_selected_sensors()

    # test_ccqr_keeps_qr_out_of_the_body: the noisy synthetic cylinder whose body cells vary most.
    with Dataset(_noisy_synthetic("cylinder", workdir / "cylinder.h5", solid_boost=30.0)) as ds:
        solid = ~ds.benchmark.fluid_mask().ravel()
        X = observed_snapshots(ds).astype(np.float64)
    X -= X.mean(axis=0)
    out.update(input_entries("ccqr_cylinder.input", X))
    unconstrained = ps.SSPOR(basis=ps.basis.SVD(n_basis_modes=8, algorithm="arpack", random_state=0), n_sensors=8)
    out["ccqr_cylinder.unconstrained"] = unconstrained.fit(X, quiet=True).get_selected_sensors()
    reference = ps.SSPOR(basis=ps.basis.SVD(n_basis_modes=8, algorithm="arpack", random_state=0),
                         optimizer=ps.optimizers.CCQR(sensor_costs=np.where(solid, 1e6, 0.0)), n_sensors=8)
    out["ccqr_cylinder.sensors"] = reference.fit(X, quiet=True).get_selected_sensors()

    # test_pivots_equal_pysensors_optimizers_on_random_bases
    for case in PIVOT_CASES:
        basis, costs = _pivot_case(case)
        r = basis.shape[1]
        out.update(input_entries(f"pivots.{case}.basis", basis))
        out.update(input_entries(f"pivots.{case}.costs", costs))
        out[f"pivots.{case}.ccqr"] = ps.optimizers.CCQR(sensor_costs=costs).fit(basis).get_sensors()[:r]
        out[f"pivots.{case}.qr"] = ps.optimizers.QR().fit(basis).get_sensors()[:r]
    return out


def main() -> None:
    try:
        found = {name: metadata.version(name) for name in PACKAGES}
    except metadata.PackageNotFoundError as exc:
        sys.exit(f"{exc.name} is not installed: pip install ezyrb==1.3.3 python-sensors==0.4.3")
    refs = {"versions": np.array(json.dumps(found, sort_keys=True))}
    with tempfile.TemporaryDirectory() as tmp:
        refs.update(pdmd_references())
        refs.update(agents_references(Path(tmp)))
    fd, partial = tempfile.mkstemp(dir=HERE, suffix=".npz.partial")
    os.close(fd)
    try:
        with open(partial, "wb") as f:
            np.savez_compressed(f, **refs)
        os.chmod(partial, 0o644)
        os.replace(partial, REFERENCES)
    finally:
        if os.path.exists(partial):
            os.unlink(partial)
    print(f"{REFERENCES}: {len(refs)} arrays, {REFERENCES.stat().st_size / 1024:.0f} KiB, {found}")


if __name__ == "__main__":
    sys.path.insert(0, str(HERE.parents[1]))  # the repository root, for `tests`
    main()
