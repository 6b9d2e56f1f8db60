"""Robust least-squares sphere and ellipsoid fits to points (the mesh stage's global shape)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


def sphere_fit(points: np.ndarray, iterations: int = 5) -> np.ndarray | None:
    """Algebraic sphere fit, reweighted to resist outliers; ``None`` if degenerate."""
    a = np.hstack([2 * points, np.ones((len(points), 1))])
    b = (points**2).sum(axis=1)
    w = np.ones(len(points))
    sol = None
    for _ in range(iterations):
        sw = np.sqrt(w)[:, None]
        sol, *_ = np.linalg.lstsq(a * sw, b * sw[:, 0], rcond=None)
        c = sol[:3]
        r2 = sol[3] + c @ c
        if not r2 > 0:
            return None
        res = np.linalg.norm(points - c, axis=1) - math.sqrt(r2)
        s = 1.4826 * np.median(np.abs(res)) + 1e-12
        w = 1.0 / np.maximum(1.0, np.abs(res) / (2 * s))
    return None if sol is None else sol[:3]


@dataclass(frozen=True)
class Ellipsoid:
    """{p : (p - centre)ᵀ A (p - centre) = 1}, A symmetric positive definite."""

    centre: np.ndarray
    a: np.ndarray

    def radius(self, origin: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        """Distance from ``origin`` (inside) along unit ``dirs`` to the ellipsoid."""
        o = origin - self.centre
        qa = np.einsum("ij,jk,ik->i", dirs, self.a, dirs)
        qb = 2.0 * dirs @ (self.a @ o)
        qc = float(o @ self.a @ o) - 1.0
        disc = np.maximum(qb * qb - 4 * qa * qc, 0.0)
        return (-qb + np.sqrt(disc)) / (2 * qa)

    def contains(self, p: np.ndarray) -> bool:
        d = p - self.centre
        return float(d @ self.a @ d) < 1.0

    @classmethod
    def sphere(cls, centre: np.ndarray, radius: float) -> Ellipsoid:
        return cls(np.asarray(centre, float), np.eye(3) / radius**2)


def fit_ellipsoid(points: np.ndarray, iterations: int = 4) -> Ellipsoid | None:
    """Robust algebraic ellipsoid fit (trace-constrained quadric); ``None`` if not an ellipsoid."""
    m = points.mean(axis=0)
    s = float(np.sqrt(((points - m) ** 2).sum(axis=1).mean()))
    x, y, z = ((points - m) / s).T
    d = np.stack([x * x + y * y - 2 * z * z, x * x + z * z - 2 * y * y, 2 * x * y, 2 * x * z,
                  2 * y * z, 2 * x, 2 * y, 2 * z, np.ones_like(x)], axis=1)
    rhs = x * x + y * y + z * z
    w = np.ones(len(x))
    ell = None
    for _ in range(iterations):
        sw = np.sqrt(w)
        # A little ridge keeps the fit defined when only part of the wall was seen.
        lhs = (d * sw[:, None]).T @ (d * sw[:, None]) + 1e-6 * len(x) * np.eye(9)
        u = np.linalg.solve(lhs, (d * sw[:, None]).T @ (rhs * sw))
        q = np.array([[u[0] + u[1] - 1, u[2], u[3]], [u[2], u[0] - 2 * u[1] - 1, u[4]],
                      [u[3], u[4], u[1] - 2 * u[0] - 1]])
        lin = u[5:8]
        try:
            c = -np.linalg.solve(q, lin)
        except np.linalg.LinAlgError:
            return None
        k = float(c @ q @ c) - u[8]
        a_mat = q / k
        ev = np.linalg.eigvalsh(a_mat)
        if not (ev.min() > 0 and ev.min() > 0.02 * ev.max()):
            return None
        ell = Ellipsoid(m + s * c, a_mat / s**2)
        p = points - ell.centre
        g = np.sqrt(np.maximum(np.einsum("ij,jk,ik->i", p, ell.a, p), 1e-300))
        res = (g - 1.0) / np.sqrt(ev.mean())  # ≈ radial distance to the ellipsoid
        sigma = 1.4826 * float(np.median(np.abs(res))) + 1e-12
        w = 1.0 / np.maximum(1.0, np.abs(res) / (2 * sigma))
    return ell
