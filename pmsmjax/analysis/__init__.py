"""Stability and design analysis of observers and drives, and a runner for large sweeps."""

from ._sweep import (
    ChunkInfo as ChunkInfo,
    SweepGrid as SweepGrid,
    grid_product as grid_product,
    run_sweep as run_sweep,
)
