"""Compatibility name: the grid-optimal reference lives in :mod:`errplan.planning.reference`."""
from .planning.reference import GridGraph, ReferenceResult, angular_bound, grid_optimum, moves, segment_cost

__all__ = ["GridGraph", "ReferenceResult", "angular_bound", "grid_optimum", "moves", "segment_cost"]
