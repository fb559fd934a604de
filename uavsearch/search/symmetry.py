"""The 8 symmetries of the square: a search's maps rotated or mirrored are another plausible search (a nadir
camera over a square grid and a square lattice has them), so training data multiplies for free.

Symmetry k in 0..7: a rotation by k % 4 quarter turns (counterclockwise seen from above, north up), then for
k >= 4 a mirror east-west. Maps are (..., rows, cols) with rows north -> south and columns west -> east (the
grid's cell order); a move or a viewpoint goes with them through `index_permutation` of its (east, north, ...)
vectors.
"""

from __future__ import annotations

import numpy as np
import torch

SYMMETRIES = 8
HALF_TURN, EAST_WEST, NORTH_SOUTH = 2, 4, 6  # the mirrors: east-west, north-south, and both (a half turn)


def mirror_symmetry(east_west: bool, north_south: bool) -> int:
    """The symmetry that mirrors east-west and / or north-south (0: neither)."""
    return {(False, False): 0, (True, False): EAST_WEST, (False, True): NORTH_SOUTH, (True, True): HALF_TURN}[
        (bool(east_west), bool(north_south))]


def square_symmetry(x, k: int, axes: tuple[int, int] = (-2, -1)):
    """A torch tensor or numpy array under symmetry k over its (rows, cols) `axes`."""
    if isinstance(x, torch.Tensor):
        x = torch.rot90(x, k % 4, dims=axes)
        return torch.flip(x, dims=(axes[1],)) if k >= 4 else x
    x = np.rot90(x, k % 4, axes=axes)
    return np.flip(x, axis=axes[1]) if k >= 4 else x


def transform_vectors(vectors: np.ndarray, k: int) -> np.ndarray:
    """(n, >= 2) vectors (east, north, anything else kept) under symmetry k."""
    v = np.array(vectors, copy=True)
    for _ in range(k % 4):
        v[:, 0], v[:, 1] = -v[:, 1], v[:, 0].copy()
    if k >= 4:
        v[:, 0] = -v[:, 0]
    return v


def index_permutation(vectors, k: int, atol: float = 1e-6) -> torch.Tensor | None:
    """(n,) long: the index each of n moves or viewpoints (their (east, north, ...) vectors: action steps, or
    positions about the centre) becomes under symmetry k; None where the set is not closed under it."""
    v = np.asarray(vectors, dtype=float)
    moved = transform_vectors(v, k)
    perm = [next((b for b, w in enumerate(v) if np.abs(w - m).max() <= atol), None) for m in moved]
    return None if None in perm else torch.as_tensor(perm)


__all__ = ["EAST_WEST", "HALF_TURN", "NORTH_SOUTH", "SYMMETRIES", "index_permutation", "mirror_symmetry",
           "square_symmetry", "transform_vectors"]
