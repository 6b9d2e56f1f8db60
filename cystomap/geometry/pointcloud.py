"""Point-cloud filters: statistical outliers (robust k-nearest-neighbour distances), voxel binning."""

from __future__ import annotations

import numpy as np


def statistical_inliers(points: np.ndarray, neighbours: int, std_ratio: float) -> np.ndarray:
    """Boolean mask of the points whose mean distance to their ``neighbours`` nearest
    neighbours is at most median + ``std_ratio`` robust standard deviations (1.4826·MAD) of
    those distances; all True when ``neighbours`` is 0 or there are too few points."""
    points = np.asarray(points)
    if neighbours <= 0 or len(points) <= neighbours + 1:
        return np.ones(len(points), dtype=bool)
    from scipy.spatial import cKDTree

    d, _ = cKDTree(points).query(points, k=neighbours + 1)
    mean_d = d[:, 1:].mean(axis=1)
    med = np.median(mean_d)
    sigma = 1.4826 * np.median(np.abs(mean_d - med))
    return mean_d <= med + std_ratio * max(sigma, 1e-12)


def voxel_bin(points: np.ndarray, voxel: float) -> np.ndarray:
    """Mean of the points in each occupied voxel of side ``voxel``."""
    if voxel <= 0:
        return points
    key = np.floor((points - points.min(axis=0)) / voxel).astype(np.int64)
    _, inv, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    inv = inv.reshape(-1)
    out = np.zeros((len(counts), 3))
    np.add.at(out, inv, points)
    return out / counts[:, None]
