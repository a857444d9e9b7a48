"""A small batched lattice Boltzmann solver in torch (D2Q9 and D3Q19), CPU or CUDA.

One :class:`LBM` advances ``B`` cases at once that share the lattice and the geometry and differ in
their viscosity (one relaxation time per case): the distribution tensor is ``f`` of shape
``(B, Q, *shape)``, float32 by default. Everything is torch, so the same code runs on a GPU through
``device="cuda"``; :func:`max_batch` and :func:`chunks` split a parameter sweep into batches that fit.

Scheme (lattice units: dx = dt = 1, c_s^2 = 1/3, reference density 1):

* **Collision: BGK with a Smagorinsky eddy viscosity** (Hou et al. 1996). The local relaxation time is
  ``tau = (tau0 + sqrt(tau0^2 + 18 Cs^2 sqrt(2 Pi:Pi) / rho)) / 2`` with ``Pi`` the non-equilibrium
  momentum flux, i.e. nu_total = nu + (Cs dx)^2 |S| with the strain rate taken locally from ``Pi``.
  Why: the sphere and cylinder sweeps go to Re ~ 1000 on coarse lattices (tau0 - 1/2 ~ 1e-3), where
  plain BGK (and regularized BGK) blew up in the near-wake shear layer in an earlier experiment on
  this project; BGK + Smagorinsky with Cs = 0.15 stayed stable over Re 60-990. The eddy viscosity
  vanishes where the flow is resolved (|S| -> 0), so low-Re cases are close to plain BGK; ``Cs = 0``
  gives plain BGK (used by the Poiseuille test). KBC or cumulant collisions would be more accurate
  at the top of the range but are larger to write and test.
* **Streaming** by ``torch.roll`` (periodic wrap; non-periodic faces are overwritten by their
  boundary condition).
* **Solid nodes** (walls, bodies): half-way bounce-back. A population that would stream out of a solid
  node into a fluid node is replaced by the opposite post-collision population of the fluid node,
  so the wall sits half-way between the last fluid node and the first solid node. Solid nodes do not
  collide (their content never reaches the fluid).
* **Velocity inlet** on the x-min plane and **pressure outlet** (rho = 1) on the x-max plane, both by
  non-equilibrium extrapolation (Guo, Zheng & Shi 2002): ``f = f_eq(rho_b, u_b) + (f - f_eq)`` of the
  neighbouring plane, with the unknown of (rho_b, u_b) taken from the neighbour. (A plain equilibrium
  inlet lost mass flux in the earlier experiment; this one does not.)
* **Absorbing layer** (optional ``absorber``, strengths sigma(x) in [0, 1] along x): after each step
  ``f <- f - sigma (f - f_eq(1, u_target))``, which relaxes the flow toward the uniform target state and
  damps vortices and sound waves before they reach the outlet (a velocity inlet and an NEE pressure
  outlet both reflect sound; without the layer the impulsive start's pressure waves slosh for many
  convective times). ``extra_viscosity`` (a per-node viscosity added to every case) is the milder sponge.
* **Body force** (optional constant acceleration ``g``, for channel tests) by the velocity shift
  ``u_eq = u + tau0 g``; the reported velocity is ``u + g / 2``.
* **Force on a body** by momentum exchange over the bounce-back links (:meth:`LBM.body_force`).

``torch.compile`` of the step is optional (``compile=True``); it fuses the ~20 passes over ``f`` of
the eager step and is the way to get speed on a GPU.
"""

from __future__ import annotations

import os
from collections.abc import Iterator, Sequence
from dataclasses import dataclass

import numpy as np
import torch

CS2 = 1.0 / 3.0


@dataclass(frozen=True)
class Lattice:
    """Velocity set: integer velocities ``c`` (Q, d) and weights ``w`` (Q,)."""

    name: str
    c: np.ndarray
    w: np.ndarray

    @property
    def d(self) -> int:
        return int(self.c.shape[1])

    @property
    def q(self) -> int:
        return int(self.c.shape[0])

    @property
    def opp(self) -> np.ndarray:
        """Index of the opposite velocity of each velocity."""
        return np.array([int(np.flatnonzero((self.c == -ci).all(1))[0]) for ci in self.c])


def _d2q9() -> Lattice:
    c = np.array([[0, 0], [1, 0], [0, 1], [-1, 0], [0, -1], [1, 1], [-1, 1], [-1, -1], [1, -1]])
    w = np.array([4 / 9] + [1 / 9] * 4 + [1 / 36] * 4)
    return Lattice("D2Q9", c, w)


def _d3q19() -> Lattice:
    c = [[0, 0, 0]]
    for a in range(3):
        for s in (1, -1):
            e = [0, 0, 0]
            e[a] = s
            c.append(e)
    for a in range(3):
        for b in range(a + 1, 3):
            for sa in (1, -1):
                for sb in (1, -1):
                    e = [0, 0, 0]
                    e[a], e[b] = sa, sb
                    c.append(e)
    w = np.array([1 / 3] + [1 / 18] * 6 + [1 / 36] * 12)
    return Lattice("D3Q19", np.array(c), w)


LATTICES = {"D2Q9": _d2q9(), "D3Q19": _d3q19()}


def get_lattice(name: str | Lattice) -> Lattice:
    if isinstance(name, Lattice):
        return name
    if name not in LATTICES:
        raise ValueError(f"unknown lattice {name!r}; choose one of {', '.join(LATTICES)}")
    return LATTICES[name]


def viscosity(tau: float | np.ndarray) -> np.ndarray:
    """Lattice kinematic viscosity of relaxation time tau: nu = c_s^2 (tau - 1/2)."""
    return CS2 * (np.asarray(tau, dtype=np.float64) - 0.5)


def relaxation_time(nu: float | np.ndarray) -> np.ndarray:
    """Relaxation time of lattice viscosity nu: tau = nu / c_s^2 + 1/2."""
    return np.asarray(nu, dtype=np.float64) / CS2 + 0.5


# Memory --------------------------------------------------------------------------------------------------
# Live arrays of the size of f during one step: eager torch keeps f, f_eq, f_neq, the post-collision f,
# its opposite gather, the streamed stack, the bounce-back result and a few (Q, N) temporaries (cu, cu^2);
# a compiled step fuses most of them.
EAGER_COPIES = 10
COMPILED_COPIES = 4


def bytes_per_case(lattice: str | Lattice, shape: Sequence[int], *, compiled: bool = False, itemsize: int = 4) -> int:
    """Estimated peak device memory of one case during a step (bytes)."""
    lat = get_lattice(lattice)
    n = int(np.prod(shape))
    copies = COMPILED_COPIES if compiled else EAGER_COPIES
    return int(n * itemsize * (lat.q * copies + 4 * lat.d + 8))


def available_memory(device: str | torch.device) -> int:
    """Free memory (bytes) on ``device``: CUDA's free memory, or the host's available physical memory."""
    dev = torch.device(device)
    if dev.type == "cuda":
        free, _ = torch.cuda.mem_get_info(dev)
        return int(free)
    try:
        return int(os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"))
    except (ValueError, OSError, AttributeError):  # pragma: no cover - non-POSIX
        return 4 * 2**30


def max_batch(per_case: int, device: str | torch.device, *, fraction: float = 0.7, cap: int | None = None) -> int:
    """How many cases of ``per_case`` bytes fit in ``fraction`` of the free memory (at least 1)."""
    n = max(1, int(fraction * available_memory(device) // max(per_case, 1)))
    return min(n, cap) if cap else n


def chunks(n: int, size: int) -> Iterator[slice]:
    """Consecutive slices of at most ``size`` covering range(n)."""
    if size < 1:
        raise ValueError(f"batch size must be >= 1, got {size}")
    for start in range(0, n, size):
        yield slice(start, min(n, start + size))


# The solver ----------------------------------------------------------------------------------------------
class LBM:
    """Batched lattice Boltzmann on a box of ``shape`` nodes, ``len(nu)`` cases at once.

    ``solid`` (bool, ``shape``) marks bounce-back nodes (walls and bodies); ``body`` (bool, ``shape``,
    subset of ``solid``) the nodes whose force :meth:`body_force` reports. ``inlet_velocity`` (d,) puts a
    velocity inlet on the x-min plane and ``outlet=True`` a pressure outlet (rho = 1) on the x-max plane;
    all other faces are periodic unless covered by solid nodes. ``nu`` are lattice viscosities, one per
    case; ``extra_viscosity`` (``shape``) is added to every case's (a sponge layer); ``absorber`` (nx,)
    are the strengths of an absorbing layer along x toward ``absorber_velocity`` (default the inlet
    velocity); ``smagorinsky`` the
    constant Cs (0 for plain BGK); ``acceleration`` (d,) a uniform body force.
    """

    def __init__(
        self,
        lattice: str | Lattice,
        shape: Sequence[int],
        nu: Sequence[float] | np.ndarray,
        *,
        solid: np.ndarray | None = None,
        body: np.ndarray | None = None,
        inlet_velocity: Sequence[float] | None = None,
        outlet: bool = False,
        acceleration: Sequence[float] | None = None,
        extra_viscosity: np.ndarray | None = None,
        absorber: np.ndarray | None = None,
        absorber_velocity: Sequence[float] | None = None,
        smagorinsky: float = 0.15,
        device: str | torch.device = "cpu",
        dtype: torch.dtype = torch.float32,
        compile: bool = False,
    ) -> None:
        self.lattice = lat = get_lattice(lattice)
        self.shape = tuple(int(s) for s in shape)
        if len(self.shape) != lat.d:
            raise ValueError(f"{lat.name} needs a {lat.d}D shape, got {self.shape}")
        self._set_viscosity(nu)
        self.device = torch.device(device)
        self.dtype = dtype
        self.smagorinsky = float(smagorinsky)
        self.n = int(np.prod(self.shape))
        self._set_geometry(solid, body)
        self._set_collision(extra_viscosity)
        self._set_boundaries(inlet_velocity, outlet, acceleration)
        self._absorb = self._absorbing_layer(absorber, absorber_velocity)
        self.f = torch.empty((self.batch, lat.q, *self.shape), device=self.device, dtype=dtype)
        self.time = 0
        self._step = torch.compile(self._step_impl, dynamic=False) if compile else self._step_impl
        self.initialize()

    # Set-up, in the order __init__ runs it -----------------------------------------------------------
    def _set_viscosity(self, nu: Sequence[float] | np.ndarray) -> None:
        """The cases' lattice viscosities, their relaxation times and the batch size, checked."""
        nu = np.atleast_1d(np.asarray(nu, dtype=np.float64))
        if nu.ndim != 1 or not np.all(np.isfinite(nu)) or np.any(nu <= 0):
            raise ValueError(f"nu must be a 1D array of positive lattice viscosities, got {nu}")
        self.nu = nu
        self.tau0 = relaxation_time(nu)
        if np.any(self.tau0 < 0.5 + 1e-5):
            raise ValueError(f"relaxation time too close to 1/2: {self.tau0.min()}")
        self.batch = nu.size

    def _set_geometry(self, solid: np.ndarray | None, body: np.ndarray | None) -> None:
        """The lattice's velocities on the device, the solid and body masks, the bounce-back links from solid
        nodes and the momentum-exchange links into the body."""
        lat, dev = self.lattice, {"device": self.device, "dtype": self.dtype}
        solid = np.zeros(self.shape, bool) if solid is None else np.asarray(solid, bool)
        body = np.zeros(self.shape, bool) if body is None else np.asarray(body, bool)
        if solid.shape != self.shape or body.shape != self.shape:
            raise ValueError("solid and body masks must have the lattice shape")
        if np.any(body & ~solid):
            raise ValueError("body nodes must be solid")
        self.solid_np, self.body_np = solid, body
        self._solid = torch.as_tensor(solid, device=self.device)
        self._fluid = (~self._solid).to(self.dtype).reshape(1, 1, self.n)
        self.c = torch.as_tensor(lat.c, **dev)
        self.w = torch.as_tensor(lat.w, **dev).reshape(1, lat.q, 1)
        self.opp = torch.as_tensor(lat.opp, device=self.device)
        # from_solid[i, x]: the node x - c_i is solid, so population i at x comes back by bounce-back.
        shifts = [tuple(int(s) for s in ci) for ci in lat.c]
        dims = tuple(range(lat.d))
        self._shifts = shifts
        self._from_solid = torch.stack([torch.roll(self._solid, s, dims) for s in shifts])
        # Momentum-exchange links into the body, restricted to the body's bounding box (+1 node).
        self._force_box = None
        if body.any():
            idx = np.nonzero(body)
            self._force_box = tuple(
                slice(max(0, int(i.min()) - 1), min(n, int(i.max()) + 2)) for i, n in zip(idx, self.shape)
            )
            from_body = torch.stack([torch.roll(torch.as_tensor(body, device=self.device), s, dims) for s in shifts])
            from_body &= ~self._solid
            self._from_body = from_body[(slice(None), *self._force_box)].to(self.dtype)

    def _set_collision(self, extra_viscosity: np.ndarray | None) -> None:
        """What the collision needs beyond the lattice: the momentum-flux components of the Smagorinsky term
        and the relaxation times per case (and per node, with a sponge's extra viscosity)."""
        lat, dev = self.lattice, {"device": self.device, "dtype": self.dtype}
        # Non-equilibrium momentum flux components (a <= b) and their multiplicity in Pi:Pi.
        pairs = [(a, b) for a in range(lat.d) for b in range(a, lat.d)]
        self._cc = torch.as_tensor(np.array([lat.c[:, a] * lat.c[:, b] for a, b in pairs], float), **dev)
        self._mult = torch.as_tensor([1.0 if a == b else 2.0 for a, b in pairs], **dev).reshape(1, -1, 1)
        self._tau0 = torch.as_tensor(self.tau0, **dev).reshape(-1, 1, 1)
        if extra_viscosity is not None:  # a sponge: nu(x) = nu_case + extra(x), shared by the cases
            extra = np.asarray(extra_viscosity, dtype=np.float64)
            if extra.shape != self.shape or np.any(extra < 0):
                raise ValueError("extra_viscosity must be a non-negative array of the lattice shape")
            self._tau0 = self._tau0 + torch.as_tensor(extra / CS2, **dev).reshape(1, 1, self.n)

    def _set_boundaries(
        self, inlet_velocity: Sequence[float] | None, outlet: bool, acceleration: Sequence[float] | None
    ) -> None:
        """The velocity inlet (x-min), the pressure outlet (x-max) and the body force."""
        lat, dev = self.lattice, {"device": self.device, "dtype": self.dtype}
        self.inlet_velocity = None
        if inlet_velocity is not None:  # (d,) uniform or (d, *shape[1:]) a profile over the inlet plane
            uin = torch.as_tensor(np.asarray(inlet_velocity, dtype=np.float64), **dev)
            if uin.shape not in ((lat.d,), (lat.d, *self.shape[1:])):
                raise ValueError(f"inlet_velocity must have shape ({lat.d},) or {(lat.d, *self.shape[1:])}")
            self.inlet_velocity = uin.reshape(1, lat.d, -1)
        self.outlet = bool(outlet)
        self.acceleration = None if acceleration is None else torch.as_tensor(acceleration, **dev).reshape(1, lat.d, 1)

    def _absorbing_layer(
        self, absorber: np.ndarray | None, absorber_velocity: Sequence[float] | None
    ) -> tuple[int, torch.Tensor, torch.Tensor] | None:
        """The absorbing layer along x as ``(first x index, sigma(x), f_eq of the target state)``, or None.

        After each step ``f <- f - sigma(x) (f - f_eq(1, u_target))`` where sigma > 0; the target velocity is
        ``absorber_velocity``, else the inlet's mean velocity, else 0.
        """
        if absorber is None:
            return None
        lat, dev = self.lattice, {"device": self.device, "dtype": self.dtype}
        sigma = np.asarray(absorber, dtype=np.float64)
        if sigma.shape != (self.shape[0],) or np.any(sigma < 0) or np.any(sigma > 1):
            raise ValueError("absorber must be an array of strengths in [0, 1] along x")
        start = int(np.flatnonzero(sigma > 0)[0]) if np.any(sigma > 0) else self.shape[0]
        if absorber_velocity is not None:
            target = torch.as_tensor(absorber_velocity, **dev).reshape(1, lat.d, 1)
        elif self.inlet_velocity is not None:
            target = self.inlet_velocity.mean(2, keepdim=True)
        else:
            target = torch.zeros((1, lat.d, 1), **dev)
        fe = self.equilibrium(torch.ones((1, 1, 1), **dev), target).reshape(1, lat.q, *([1] * lat.d))
        sig = torch.as_tensor(sigma[start:], **dev).reshape(1, 1, -1, *([1] * (lat.d - 1)))
        return start, sig, fe

    # Equilibrium and moments ---------------------------------------------------------------------------
    def equilibrium(self, rho: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """f_eq of rho (B, 1, N) and u (B, d, N): (B, Q, N), second order in u."""
        cu = torch.matmul(self.c, u)
        usq = (u * u).sum(1, keepdim=True)
        return self.w * rho * (1.0 + 3.0 * cu + 4.5 * cu * cu - 1.5 * usq)

    def _moments(self, f: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        rho = f.sum(1, keepdim=True)
        return rho, torch.matmul(self.c.T, f) / rho

    def initialize(self, velocity: np.ndarray | torch.Tensor | None = None, rho: float = 1.0) -> None:
        """Set f to equilibrium at density ``rho`` and ``velocity`` ((d, *shape) or (B, d, *shape); 0 if None).

        The velocity is zeroed on solid nodes."""
        d = self.lattice.d
        u = torch.zeros((self.batch, d, self.n), device=self.device, dtype=self.dtype)
        if velocity is not None:
            v = torch.as_tensor(velocity, device=self.device, dtype=self.dtype)
            u[:] = v.reshape(-1, d, self.n)
        u = u * self._fluid
        r = torch.full((self.batch, 1, self.n), float(rho), device=self.device, dtype=self.dtype)
        self.f = self.equilibrium(r, u).reshape(self.batch, self.lattice.q, *self.shape).contiguous()
        self.time = 0

    # The step ------------------------------------------------------------------------------------------
    def _step_impl(self, f: torch.Tensor) -> torch.Tensor:
        lat = self.lattice
        b, q = f.shape[:2]
        ff = f.reshape(b, q, self.n)
        rho = ff.sum(1, keepdim=True)
        u = torch.matmul(self.c.T, ff) / rho
        if self.acceleration is not None:
            u = u + self._tau0 * self.acceleration
        feq = self.equilibrium(rho, u)
        fneq = ff - feq
        if self.smagorinsky > 0:
            pi = torch.matmul(self._cc, fneq)
            pipi = (pi * pi * self._mult).sum(1, keepdim=True)
            eddy = 18.0 * self.smagorinsky**2 * torch.sqrt(2.0 * pipi) / rho
            tau = 0.5 * (self._tau0 + torch.sqrt(self._tau0**2 + eddy))
        else:
            tau = self._tau0
        post = ff - (self._fluid / tau) * fneq
        post = post.reshape(b, q, *self.shape)
        dims = tuple(range(1, lat.d + 1))
        streamed = torch.stack(
            [torch.roll(post[:, i], s, dims) if any(s) else post[:, i] for i, s in enumerate(self._shifts)], dim=1
        )
        out = torch.where(self._from_solid, post[:, self.opp], streamed)
        if self.inlet_velocity is not None:
            nb = out[:, :, 1].reshape(b, q, -1)
            rho1, u1 = self._moments(nb)
            ub = self.inlet_velocity.expand_as(u1)
            out[:, :, 0] = (self.equilibrium(rho1, ub) + nb - self.equilibrium(rho1, u1)).reshape(out[:, :, 0].shape)
        if self.outlet:
            nb = out[:, :, -2].reshape(b, q, -1)
            rho1, u1 = self._moments(nb)
            out[:, :, -1] = (self.equilibrium(torch.ones_like(rho1), u1) + nb - self.equilibrium(rho1, u1)).reshape(
                out[:, :, -1].shape
            )
        if self._absorb is not None:
            start, sig, fe = self._absorb
            layer = out[:, :, start:]
            out[:, :, start:] = layer - sig * (layer - fe)
        return out

    def step(self, n: int = 1) -> None:
        """Advance every case by ``n`` time steps."""
        for _ in range(int(n)):
            self.f = self._step(self.f)
        self.time += int(n)

    # Observables ---------------------------------------------------------------------------------------
    def macroscopic(self) -> tuple[torch.Tensor, torch.Tensor]:
        """(rho (B, *shape), u (B, d, *shape)); u includes the half-force shift, zero on solid nodes."""
        b, q = self.f.shape[:2]
        rho, u = self._moments(self.f.reshape(b, q, self.n))
        if self.acceleration is not None:
            u = u + 0.5 * self.acceleration
        u = u * self._fluid
        return rho.reshape(b, *self.shape), u.reshape(b, self.lattice.d, *self.shape)

    def body_force(self) -> torch.Tensor:
        """Force on the body nodes (B, d), lattice units, by momentum exchange.

        Each link from a fluid node x into the body carries 2 c_i f_i^post(x); after the step the bounced
        population is f_j(x) = f_i^post(x) with c_j = -c_i, so F = -2 sum_{x, j from body} c_j f_j(x)."""
        if self._force_box is None:
            raise ValueError("no body nodes were given")
        fb = self.f[(slice(None), slice(None), *self._force_box)]
        per_dir = (fb * self._from_body).flatten(2).sum(-1)  # (B, Q)
        return -2.0 * per_dir @ self.c

    def mass(self) -> torch.Tensor:
        """Total mass on fluid nodes per case (B,)."""
        b, q = self.f.shape[:2]
        return (self.f.reshape(b, q, self.n) * self._fluid).sum((1, 2))

    def is_finite(self) -> torch.Tensor:
        """Per case: whether every fluid population is finite (B,) bool."""
        b, q = self.f.shape[:2]
        ff = self.f.reshape(b, q, self.n)
        return torch.isfinite(torch.where(self._fluid.bool(), ff, 0.0)).all(2).all(1)


def poiseuille_profile(height: float, y: np.ndarray, g: float, nu: float) -> np.ndarray:
    """Exact channel profile u(y) = g y (H - y) / (2 nu) for walls at y = 0 and y = H."""
    return g * y * (height - y) / (2.0 * nu)


def mlups(n_cases: int, n_nodes: int, n_steps: int, seconds: float) -> float:
    """Million lattice-node updates per second."""
    return n_cases * n_nodes * n_steps / max(seconds, 1e-12) / 1e6


__all__ = [
    "CS2",
    "LATTICES",
    "LBM",
    "Lattice",
    "available_memory",
    "bytes_per_case",
    "chunks",
    "get_lattice",
    "max_batch",
    "mlups",
    "poiseuille_profile",
    "relaxation_time",
    "viscosity",
]
