"""Geometry, cell types and paper sensor layouts of the CFD benchmarks (cylinder, dambreak, sphere).

Expected values come from the SPEC table, from closed-form geometry (cell counts of a rectangle, the
lattice points of a circle or sphere counted column by column, the area/volume band a cell-centre
discretization must fall in) and from brute-force distances, never from the layout code itself.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from dks_gym.benchmarks import GeneratorUnavailable, get_benchmark

CFD = ("cylinder", "dambreak", "sphere")
COUNTS = (16, 8, 4)


def centres(bench, flat: np.ndarray) -> np.ndarray:
    """Physical cell centres of flat indices, (n, ndim)."""
    idx = np.unravel_index(np.asarray(flat), bench.grid)
    return np.stack([c[i] for c, i in zip(bench.coords(), idx)], axis=1)


def spacing(bench) -> np.ndarray:
    return np.array([c[1] - c[0] for c in bench.coords()])


def flip(flat: np.ndarray, grid: tuple[int, ...], axis: int) -> set[int]:
    idx = list(np.unravel_index(np.asarray(flat), grid))
    idx[axis] = grid[axis] - 1 - idx[axis]
    return set(np.ravel_multi_index(tuple(idx), grid).tolist())


# SPEC section 1 --------------------------------------------------------------------------------------
SPEC = {
    "cylinder": dict(env_id="DKS/Cylinder-v0", grid=(64, 64), channels=("u", "v", "p"), param_name="Re",
                     param_range=(59.5, 990.5), dt=0.5),
    "dambreak": dict(env_id="DKS/Dambreak-v0", grid=(64, 64), channels=("Ux", "Uy", "p_rgh", "p", "alpha.water"),
                     param_name="nu_w", param_range=(1.0e-3, 9.9e-2), dt=0.01),
    "sphere": dict(env_id="DKS/Sphere-v0", grid=(64, 64, 64), channels=("u", "v", "w", "p"), param_name="Re",
                   param_range=(59.5, 990.5), dt=0.5),
}


@pytest.mark.parametrize("name", CFD)
def test_spec_numbers(name):
    bench = get_benchmark(name)
    for key, value in SPEC[name].items():
        assert getattr(bench, key) == value, key
    assert bench.observed_channel == "p"
    assert bench.scored_channels == bench.channels
    assert (bench.n_frames, bench.n_train, bench.n_test) == (100, 90, 11)
    assert bench.solid_codes == (2,)
    if name in ("cylinder", "dambreak"):  # the OpenFOAM generators (tests/test_openfoam.py)
        assert bench.generator_available
    if not bench.generator_available:
        with pytest.raises(GeneratorUnavailable):
            bench.generate("small")


@pytest.mark.parametrize(
    "name, lows, highs", [("cylinder", (-8, -4), (16, 4)), ("dambreak", (0, 0), (0.584, 0.584)),
                          ("sphere", (-8, -4, -4), (16, 4, 4))]
)
def test_coords_are_cell_centres(name, lows, highs):
    bench = get_benchmark(name)
    coords = bench.coords()
    assert len(coords) == bench.ndim
    for c, lo, hi, n in zip(coords, lows, highs, bench.grid):
        h = (hi - lo) / n
        assert c.shape == (n,)
        np.testing.assert_allclose(c[0], lo + h / 2, rtol=0, atol=1e-12)
        np.testing.assert_allclose(c[-1], hi - h / 2, rtol=0, atol=1e-12)
        np.testing.assert_allclose(np.diff(c), h, rtol=1e-12)


# Cell types ------------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", CFD)
def test_cell_type_array(name):
    bench = get_benchmark(name)
    ct = bench.cell_type()
    assert ct.dtype == np.int8 and ct.shape == bench.grid
    assert set(np.unique(ct).tolist()) == set(bench.cell_type_codes.values())
    assert bench.cell_type() is ct  # cached
    with pytest.raises(ValueError):
        ct[0] = 0  # the cache cannot be corrupted by a caller


def _lattice_count(lo: float, h: float, a: float, b: float) -> int:
    """Number of centres lo + (j + 1/2) h strictly inside (a, b), by arithmetic."""
    if b <= a:
        return 0
    return max(0, math.ceil((b - lo) / h - 0.5) - math.floor((a - lo) / h - 0.5) - 1)


def test_cylinder_cell_counts():
    bench = get_benchmark("cylinder")
    ct = bench.cell_type()
    (x, _), (dx, dy) = bench.coords(), spacing(bench)
    nx, ny = bench.grid
    # Body: the circle's lattice points counted column by column, |y| < sqrt(R^2 - x^2).
    half_chords = [math.sqrt(1 - xi**2) for xi in x if abs(xi) < 1]
    expected_body = sum(_lattice_count(-4.0, dy, -h, h) for h in half_chords)
    body = int(np.sum(ct == 2))
    assert body == expected_body
    # Cells with centre inside the disk cover the disk of radius R - d/2 and lie in the one of radius R + d/2.
    half_diag = 0.5 * math.hypot(dx, dy)
    assert math.pi * (1 - half_diag) ** 2 <= body * dx * dy <= math.pi * (1 + half_diag) ** 2
    assert abs(body - math.pi / (dx * dy)) < 0.05 * math.pi / (dx * dy)
    # Corners belong to the walls (module docstring).
    assert np.sum(ct == 1) == 2 * nx
    assert np.sum(ct == 3) == ny - 2 and np.all(ct[0, 1:-1] == 3)
    assert np.sum(ct == 4) == ny - 2 and np.all(ct[-1, 1:-1] == 4)
    assert np.sum(ct == 0) == nx * ny - 2 * nx - 2 * (ny - 2) - body
    assert np.array_equal(ct, ct[:, ::-1])  # symmetric about y = 0


def test_sphere_cell_counts():
    bench = get_benchmark("sphere")
    ct = bench.cell_type()
    (x, _, z), (dx, dy, dz) = bench.coords(), spacing(bench)
    nx, ny, nz = bench.grid
    expected_body = 0
    for xi in x:
        for zk in z:
            r2 = 1 - xi**2 - zk**2
            if r2 > 0:
                expected_body += _lattice_count(-4.0, dy, -math.sqrt(r2), math.sqrt(r2))
    body = int(np.sum(ct == 2))
    assert body == expected_body
    half_diag = 0.5 * math.sqrt(dx**2 + dy**2 + dz**2)
    volume = body * dx * dy * dz
    assert 4 / 3 * math.pi * (1 - half_diag) ** 3 <= volume <= 4 / 3 * math.pi * (1 + half_diag) ** 3
    assert abs(volume / (4 / 3 * math.pi) - 1) < 0.05
    assert np.sum(ct == 1) == 2 * nx * nz
    assert np.all(ct[:, [0, -1], :] == 1)
    assert np.sum(ct == 3) == (ny - 2) * nz and np.sum(ct == 4) == (ny - 2) * nz
    # The z faces are not boundaries of their own.
    assert np.all(ct[1:-1, 1:-1, [0, -1]] == 0)
    for axis in (1, 2):
        assert np.array_equal(ct, np.flip(ct, axis=axis))
    # Blockage pi R^2 / (8 x 8) stated in the module docstring.
    from dks_gym.benchmarks.sphere import BLOCKAGE

    assert BLOCKAGE == pytest.approx(math.pi / 64) and round(100 * BLOCKAGE, 1) == 4.9


def test_dambreak_cell_counts():
    bench = get_benchmark("dambreak")
    ct = bench.cell_type()
    (x, y), (dx, dy) = bench.coords(), spacing(bench)
    nx, ny = bench.grid
    assert dx == pytest.approx(0.584 / 64) and dy == pytest.approx(0.584 / 64)
    # Obstacle: centres in the closed rectangle [0.292, 0.316] x [0, 0.048], counted per axis.
    n_cols = math.floor(0.316 / dx - 0.5) - math.ceil(0.292 / dx - 0.5) + 1
    n_rows = math.floor(0.048 / dy - 0.5) + 1
    assert (n_cols, n_rows) == (3, 5)
    obstacle = ct == 2
    assert obstacle.sum() == n_cols * n_rows
    cols, rows = np.nonzero(obstacle)
    assert x[cols].min() >= 0.292 and x[cols].max() <= 0.316 and y[rows].max() <= 0.048 and rows.min() == 0
    assert np.all(ct[[0, -1], :] == 1)  # side walls, full height (top corners included)
    bottom_fluid = ~obstacle[:, 0]
    assert np.all(ct[bottom_fluid, 0] == 1)
    assert np.sum(ct == 1) == 2 * ny + (nx - 2) - n_cols
    assert np.sum(ct == 3) == nx - 2 and np.all(ct[1:-1, -1] == 3)


# Layouts ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", CFD)
@pytest.mark.parametrize("m", COUNTS)
def test_layout_is_valid(name, m):
    bench = get_benchmark(name)
    layout = bench.paper_layout(m)
    assert layout.shape == (m,) and np.issubdtype(layout.dtype, np.integer)
    assert len(set(layout.tolist())) == m
    assert np.all((layout >= 0) & (layout < bench.n_cells))
    solid = np.isin(bench.cell_type().ravel()[layout], bench.solid_codes)
    assert not solid.any()
    np.testing.assert_array_equal(layout, bench.paper_layout(m))  # deterministic
    np.testing.assert_array_equal(layout, np.concatenate(list(bench.layout_groups(m).values())))


@pytest.mark.parametrize("name", CFD)
def test_every_supported_count_is_valid(name):
    bench = get_benchmark(name)
    for m in range(1, 33):
        layout = bench.paper_layout(m)
        assert len(set(layout.tolist())) == m
        assert not np.isin(bench.cell_type().ravel()[layout], bench.solid_codes).any()


@pytest.mark.parametrize("name", CFD)
@pytest.mark.parametrize("bad", [0, -1, 33, 2.5, 16.0, "16", True, None])
def test_bad_sensor_count_raises(name, bad):
    with pytest.raises(ValueError, match="m"):
        get_benchmark(name).paper_layout(bad)


def _within_one_cell_of_body(bench, flat: np.ndarray) -> np.ndarray:
    body = centres(bench, np.flatnonzero(bench.cell_type().ravel() == 2))
    pts = centres(bench, flat)
    dist = np.sqrt(((pts[:, None, :] - body[None, :, :]) ** 2).sum(-1)).min(axis=1)
    return dist <= np.linalg.norm(spacing(bench)) + 1e-9


@pytest.mark.parametrize("name", ("cylinder", "sphere"))
@pytest.mark.parametrize("m", COUNTS)
def test_body_layout_geometry(name, m):
    bench = get_benchmark(name)
    groups = bench.layout_groups(m)
    assert set(groups) == {"surface", "wake"}
    layout = bench.paper_layout(m)
    assert set(layout.tolist()) == flip(layout, bench.grid, axis=1)  # y -> -y
    if name == "sphere":
        assert set(layout.tolist()) == flip(layout, bench.grid, axis=2)  # z -> -z
    surface, wake = groups["surface"], groups["wake"]
    assert len(surface) >= len(wake) >= len(surface) - 4 and len(surface) > 0
    # Surface sensors touch the body, on its rear half.
    assert np.all(_within_one_cell_of_body(bench, surface))
    assert np.all(centres(bench, surface)[:, 0] > 0)
    if name == "sphere":  # on the diagonal meridians |y| = |z|, which keep the quadruples apart
        ps = centres(bench, surface)
        np.testing.assert_array_equal(np.abs(ps[:, 1]), np.abs(ps[:, 2]))
    # Wake sensors are behind the body, in the near wake.
    if len(wake):
        pw = centres(bench, wake)
        assert np.all((pw[:, 0] > 1.0) & (pw[:, 0] <= 5.0))
        # ... on the rows (and, for the sphere, layers) nearest to +-R/2, where the vortices pass.
        for axis in range(1, bench.ndim):
            assert np.all(np.abs(np.abs(pw[:, axis]) - 0.5) <= spacing(bench)[axis] / 2)
        columns = np.unique(np.unravel_index(wake, bench.grid)[0])
        if len(columns) > 2:
            steps = np.diff(columns)
            assert steps.max() - steps.min() <= 1  # equidistant as far as the grid allows


def test_cylinder_surface_angles_spread_over_rear_half():
    """For m = 16 the four upper surface sensors lie at increasing angles inside (0, 90) degrees."""
    bench = get_benchmark("cylinder")
    surface = bench.layout_groups(16)["surface"]
    pts = centres(bench, surface)
    upper = pts[pts[:, 1] > 0]
    angles = np.degrees(np.arctan2(upper[:, 1], upper[:, 0]))
    assert len(angles) == 4 and np.all(np.diff(angles) > 0) and angles.min() > 0 and angles.max() < 90
    # Targets are 11.25, 33.75, 56.25, 78.75 degrees; anisotropic cells (dx = 3 dy) allow ~ +-15.
    np.testing.assert_allclose(angles, [11.25, 33.75, 56.25, 78.75], atol=15)


@pytest.mark.parametrize("m", COUNTS)
def test_dambreak_layout_geometry(m):
    bench = get_benchmark("dambreak")
    groups = bench.layout_groups(m)
    assert set(groups) == {"bottom", "obstacle"}
    ct = bench.cell_type()
    obstacle_cells = np.flatnonzero(ct.ravel() == 2)
    oi, oj = np.unravel_index(obstacle_cells, bench.grid)
    # Bottom sensors: on the bottom fluid row, off the side-wall columns.
    bi, bj = np.unravel_index(groups["bottom"], bench.grid)
    assert np.all(bj == 0) and np.all(ct[bi, bj] == 1) and np.all((bi > 0) & (bi < bench.grid[0] - 1))
    # Obstacle sensors touch the obstacle (Chebyshev distance 1 to some obstacle cell).
    si, sj = np.unravel_index(groups["obstacle"], bench.grid)
    cheb = np.maximum(np.abs(si[:, None] - oi[None]), np.abs(sj[:, None] - oj[None])).min(axis=1)
    assert np.all(cheb == 1)
    # The whole layout is mirror-symmetric about the obstacle's middle column.
    centre = (oi.min() + oi.max()) // 2
    i, j = np.unravel_index(bench.paper_layout(m), bench.grid)
    assert set(zip(i.tolist(), j.tolist())) == set(zip((2 * centre - i).tolist(), j.tolist()))
    # Bottom sensors are equidistant in x across the obstacle, as far as the grid allows.
    if len(bi) > 2:
        steps = np.diff(np.sort(bi))
        assert steps.max() - steps.min() <= 1
    assert len(groups["bottom"]) >= len(groups["obstacle"])


def test_dambreak_sixteen_sensors_cover_both_faces_and_top():
    bench = get_benchmark("dambreak")
    si, sj = np.unravel_index(bench.layout_groups(16)["obstacle"], bench.grid)
    oi = np.flatnonzero(np.any(bench.cell_type() == 2, axis=1))
    top = np.flatnonzero(np.any(bench.cell_type() == 2, axis=0)).max() + 1
    assert np.any(si == oi.min() - 1) and np.any(si == oi.max() + 1) and np.any(sj == top)
    bi = np.unravel_index(bench.layout_groups(16)["bottom"], bench.grid)[0]
    assert len(bi) == 10 and np.all(np.diff(np.sort(bi)) == 6)
