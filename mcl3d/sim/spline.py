"""Piecewise quintic Hermite curves: C2-smooth channels with analytic first and second derivatives.

Each segment matches values, rates and second derivatives at its knots, so the whole curve
is C2; a knot with zero rate and acceleration is an exact stop (no overshoot between stops).
"""

from __future__ import annotations

import numpy as np


def catmull_rom_rates(t: np.ndarray, values: np.ndarray, stops: np.ndarray) -> np.ndarray:
    """Knot rates (K, C): central differences, zero at the ends and at stops."""
    rates = np.zeros_like(values)
    if len(t) > 2:
        rates[1:-1] = (values[2:] - values[:-2]) / (t[2:] - t[:-2])[:, None]
    rates[stops] = 0.0
    return rates


def knot_accelerations(t: np.ndarray, rates: np.ndarray, stops: np.ndarray) -> np.ndarray:
    """Second derivatives at the knots: central differences of the rates, zero at stops/ends."""
    acc = np.zeros_like(rates)
    if len(t) > 2:
        acc[1:-1] = (rates[2:] - rates[:-2]) / (t[2:] - t[:-2])[:, None]
    acc[stops] = 0.0
    return acc


class QuinticHermite:
    """Channels (C of them) through knots (K,) with values (K, C), rates (K, C) and optional
    second derivatives (K, C) (zero when omitted)."""

    def __init__(self, t_knots: np.ndarray, values: np.ndarray, rates: np.ndarray,
                 accelerations: np.ndarray | None = None) -> None:
        t = np.asarray(t_knots, dtype=np.float64)
        if t.ndim != 1 or len(t) < 2 or np.any(np.diff(t) <= 0):
            raise ValueError("knot times must be strictly increasing, at least two")
        p = np.asarray(values, dtype=np.float64)
        v = np.asarray(rates, dtype=np.float64)
        h = np.diff(t)[:, None]
        dp = p[1:] - p[:-1]
        v0, v1 = h * v[:-1], h * v[1:]
        a = np.zeros_like(p) if accelerations is None else np.asarray(accelerations, np.float64)
        a0, a1 = h**2 * a[:-1], h**2 * a[1:]
        # p(s) = sum c_i s^i with s = (t - t0) / h on each segment
        self._c = np.stack([p[:-1], v0, 0.5 * a0,
                            10 * dp - 6 * v0 - 4 * v1 - 1.5 * a0 + 0.5 * a1,
                            -15 * dp + 8 * v0 + 7 * v1 + 1.5 * a0 - a1,
                            6 * dp - 3 * v0 - 3 * v1 - 0.5 * a0 + 0.5 * a1], axis=1)
        self.t = t
        self._h = h[:, 0]

    @property
    def t_start(self) -> float:
        return float(self.t[0])

    @property
    def t_end(self) -> float:
        return float(self.t[-1])

    def __call__(self, t: np.ndarray, order: int = 0) -> np.ndarray:
        """Values (order 0), first (1) or second (2) derivatives at times t, shape (N, C).
        Times outside the knots are clamped (the curve holds still beyond its ends)."""
        t = np.atleast_1d(np.asarray(t, dtype=np.float64))
        tc = np.clip(t, self.t[0], self.t[-1])
        seg = np.clip(np.searchsorted(self.t, tc, side="right") - 1, 0, len(self._h) - 1)
        h = self._h[seg][:, None]
        s = ((tc - self.t[seg]) / self._h[seg])[:, None]
        c = self._c[seg]
        if order == 0:
            return c[:, 0] + s * (c[:, 1] + s * (c[:, 2] + s * (c[:, 3] + s * (
                c[:, 4] + s * c[:, 5]))))
        outside = ((t < self.t[0]) | (t > self.t[-1]))[:, None]
        if order == 1:
            d = c[:, 1] + s * (2 * c[:, 2] + s * (3 * c[:, 3] + s * (
                4 * c[:, 4] + s * 5 * c[:, 5])))
            return np.where(outside, 0.0, d / h)
        if order == 2:
            d = 2 * c[:, 2] + s * (6 * c[:, 3] + s * (12 * c[:, 4] + s * 20 * c[:, 5]))
            return np.where(outside, 0.0, d / h**2)
        raise ValueError("order must be 0, 1 or 2")
