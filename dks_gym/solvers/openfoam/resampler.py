"""From OpenFOAM's cells to the benchmark's uniform grid: piecewise-linear interpolation on a Delaunay
triangulation of the cell centres plus the boundary-face centres.

The weights are computed once per mesh (:func:`build_resampler`) and then applied to every frame of every
run as a sparse matrix (:class:`Resampler`).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from scipy import sparse
from scipy.spatial import Delaunay, cKDTree

from .reader import MeshGeometry

#: A value in a boundary specification meaning "take the value of the face's owner cell" (zero gradient).
OWNER = None


@dataclass(frozen=True)
class Resampler:
    """Linear map from OpenFOAM cell values to the uniform grid, one sparse matrix and offset per channel.

    ``grid_value[c] = matrices[c] @ cell_value[c] + offsets[c]``; solid grid cells (inside a body or an
    obstacle) get 0 in every channel. Build it with :func:`build_resampler`.
    """

    grid: tuple[int, ...]
    channels: tuple[str, ...]
    matrices: tuple[sparse.csr_matrix, ...]
    offsets: np.ndarray  # (C, n_grid_cells)
    mesh: MeshGeometry

    @property
    def n_cells(self) -> int:
        return self.mesh.n_cells

    def __call__(self, values: np.ndarray) -> np.ndarray:
        """Resample cell values (n_t, C, n_cells) to (n_t, C, *grid) float64."""
        values = np.asarray(values, dtype=np.float64)
        if values.ndim != 3 or values.shape[1:] != (len(self.channels), self.n_cells):
            raise ValueError(
                f"expected cell values of shape (n_t, {len(self.channels)}, {self.n_cells}), got {values.shape}; "
                "was the run's mesh built with the same settings as the resampler's?"
            )
        out = np.empty((values.shape[0], len(self.channels), int(np.prod(self.grid))))
        for c, matrix in enumerate(self.matrices):
            out[:, c] = (matrix @ values[:, c].T).T + self.offsets[c]
        return out.reshape(values.shape[0], len(self.channels), *self.grid)


def build_resampler(
    mesh: MeshGeometry,
    coords: tuple[np.ndarray, np.ndarray],
    solid: np.ndarray,
    channels: Sequence[str],
    boundary_values: Mapping[str, Mapping[str, float | None]],
) -> Resampler:
    """Interpolation weights from ``mesh`` to the grid of cell centres ``coords`` (x, y), computed once.

    The nodes are the cell centres plus the centres of the boundary faces of every patch in
    ``boundary_values``, which maps patch -> channel -> the fixed boundary value, or :data:`OWNER` to
    take the value of the face's owner cell (zero-gradient patches). Including the boundary faces keeps
    grid points near walls and bodies inside the triangulation, and no-slip walls pull the velocity to
    zero there. Grid cells with ``solid`` True are set to 0. A grid point outside every triangle (only
    possible if a patch is left out) takes its nearest node's value.
    """
    channels = tuple(channels)
    missing = [p for p in mesh.boundary if p not in boundary_values]
    if missing:
        raise ValueError(f"boundary_values lacks patch(es) {missing}; give every non-empty patch its values")
    x, y = (np.asarray(c, dtype=np.float64) for c in coords)
    grid = (x.size, y.size)
    solid = np.asarray(solid, dtype=bool)
    if solid.shape != grid:
        raise ValueError(f"solid mask has shape {solid.shape}, expected the grid shape {grid}")
    targets = np.stack([a.ravel() for a in np.meshgrid(x, y, indexing="ij")], axis=1)
    fluid = np.flatnonzero(~solid.ravel())
    nodes, node_cell, node_fixed = interpolation_nodes(mesh, channels, boundary_values)
    rows, cols, weights = interpolation_weights(nodes, targets[fluid], fluid)
    matrices, offsets = channel_maps(rows, cols, weights, node_cell, node_fixed, targets.shape[0], mesh.n_cells)
    return Resampler(grid=grid, channels=channels, matrices=matrices, offsets=offsets, mesh=mesh)


def interpolation_nodes(
    mesh: MeshGeometry, channels: tuple[str, ...], boundary_values: Mapping[str, Mapping[str, float | None]]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The interpolation nodes (n_nodes, 2): cell centres, then the face centres patch by patch; each node's
    owner cell (n_nodes,) (cells own themselves); and its fixed value per channel (C, n_nodes), NaN where the
    node takes its cell's value."""
    patch_names = list(mesh.boundary)
    face_xy = [mesh.boundary[p][0] for p in patch_names]
    face_owner = [mesh.boundary[p][1] for p in patch_names]
    nodes = np.concatenate([mesh.cell_centres, *face_xy])
    n_cells = mesh.n_cells
    node_cell = np.concatenate([np.arange(n_cells), *face_owner])
    node_fixed = np.full((len(channels), nodes.shape[0]), np.nan)
    start = n_cells
    for p, xy in zip(patch_names, face_xy):
        spec = boundary_values[p]
        unknown = set(spec) - set(channels)
        if unknown:
            raise ValueError(f"boundary_values[{p!r}] names unknown channel(s) {sorted(unknown)}; channels: {channels}")
        for c, ch in enumerate(channels):
            value = spec.get(ch, OWNER)
            if value is not OWNER:
                node_fixed[c, start : start + len(xy)] = float(value)
        start += len(xy)
    return nodes, node_cell, node_fixed


def interpolation_weights(
    nodes: np.ndarray, points: np.ndarray, rows_of_points: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(rows, node indices, weights)`` of the piecewise-linear interpolation from ``nodes`` to ``points``:
    barycentric weights in the Delaunay triangle holding a point, weight 1 on the nearest node for a point
    outside every triangle. ``rows_of_points`` are the points' row numbers in the output."""
    tri = Delaunay(nodes)
    simplex = tri.find_simplex(points)
    rows, cols, weights = [], [], []
    inside = simplex >= 0
    if np.any(inside):
        s = simplex[inside]
        transform = tri.transform[s]
        bary = np.einsum("nij,nj->ni", transform[:, :2], points[inside] - transform[:, 2])
        bary = np.concatenate([bary, 1.0 - bary.sum(axis=1, keepdims=True)], axis=1)
        rows.append(np.repeat(rows_of_points[inside], 3))
        cols.append(tri.simplices[s].ravel())
        weights.append(bary.ravel())
    if np.any(~inside):
        _, nearest = cKDTree(nodes).query(points[~inside])
        rows.append(rows_of_points[~inside])
        cols.append(np.asarray(nearest, dtype=np.int64))
        weights.append(np.ones(int((~inside).sum())))
    rows_a, nodes_a, w_a = np.concatenate(rows), np.concatenate(cols), np.concatenate(weights)
    # Tiny negative barycentric weights come from points on an edge; they are rounding, not extrapolation.
    return rows_a, nodes_a, np.where(np.abs(w_a) < 1e-12, 0.0, w_a)


def channel_maps(
    rows: np.ndarray,
    nodes: np.ndarray,
    weights: np.ndarray,
    node_cell: np.ndarray,
    node_fixed: np.ndarray,
    n_grid: int,
    n_cells: int,
) -> tuple[tuple[sparse.csr_matrix, ...], np.ndarray]:
    """Per channel, the sparse map from cell values to the grid and the offset (n_grid,) of the fixed
    boundary values: the weight of a node with a fixed value goes to the offset, any other to its cell."""
    matrices, offsets = [], np.zeros((node_fixed.shape[0], n_grid))
    for c in range(node_fixed.shape[0]):
        fixed = node_fixed[c, nodes]
        is_fixed = ~np.isnan(fixed)
        np.add.at(offsets[c], rows[is_fixed], weights[is_fixed] * fixed[is_fixed])
        keep = ~is_fixed
        matrix = sparse.csr_matrix((weights[keep], (rows[keep], node_cell[nodes[keep]])), shape=(n_grid, n_cells))
        matrix.sum_duplicates()
        matrices.append(matrix)
    return tuple(matrices), offsets
