"""External solvers behind the CFD benchmarks' data generators (OpenFOAM for the cylinder and the dambreak).

Benchmarks import these lazily inside ``generate`` so that dks-gym imports without OpenFOAM or fluidfoam.
"""
