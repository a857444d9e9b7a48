"""The solvers behind the benchmarks' data generators: OpenFOAM for the cylinder and the dambreak, the lattice
Boltzmann solver for the sphere; and the Kuramoto-Sivashinsky solver (:mod:`.kuramoto_sivashinsky`, numpy only)
that generates a flow outside the four benchmarks.

The solvers import the benchmarks (for their geometry), never the other way round: each benchmark names its
generator here by entry point (``"dks_gym.solvers.cylinder_case:generate_cylinder"``), resolved on the first
``generate``, so that dks-gym imports without OpenFOAM, fluidfoam or the solvers' torch code.
"""
