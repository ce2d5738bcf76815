"""Tetrahedral meshes and a nearly-incompressible hyperelastic gravity solver."""

from .discretize import FORMULATIONS, Discretization, discretize
from .fields import edge_midpoint_displacement_mm
from .materials import FebioNeoHookean, MooneyRivlin, NeoHookean, Volumetric
from .mesh import MeshError, MeshQuality, TetMesh, boundary_faces, mesh_quality
from .model import Clamped, Constrained, ElasticSupport, Model, Sliding
from .prestress import (
    RETRY_OPTIONS,
    PostureSolve,
    Prestress,
    compute_prestress,
    solve_posture,
    solve_prestressed,
)
from .solver import ConvergenceError, Solution, SolverOptions, displacement_at, solve

__all__ = [
    "FORMULATIONS",
    "Clamped",
    "Constrained",
    "ConvergenceError",
    "Discretization",
    "ElasticSupport",
    "FebioNeoHookean",
    "MeshError",
    "MeshQuality",
    "Model",
    "MooneyRivlin",
    "NeoHookean",
    "PostureSolve",
    "Prestress",
    "RETRY_OPTIONS",
    "Sliding",
    "Solution",
    "SolverOptions",
    "TetMesh",
    "Volumetric",
    "boundary_faces",
    "compute_prestress",
    "discretize",
    "displacement_at",
    "edge_midpoint_displacement_mm",
    "mesh_quality",
    "solve",
    "solve_posture",
    "solve_prestressed",
]
