"""Fit the polynomial coefficients used by veila-geom's fastmath module.

atan(a) ~= a * P(a^2) on [0, 1], and pi/2 - asin(x) ~= sqrt(1 - x) * Q(x) on [0, 1], by iteratively
reweighted least squares towards the minimax solution. Run: python3 tools/fit_fastmath.py
"""
import numpy as np


def fit(X, y, iters=60):
    w = np.ones_like(y)
    for _ in range(iters):
        c, *_ = np.linalg.lstsq(X * w[:, None], y * w, rcond=None)
        e = X @ c - y
        w = w * (1 + np.abs(e) / np.abs(e).max())
    return c, np.abs(e).max()


a = np.linspace(0, 1, 20001)
c, err = fit(np.stack([a * (a * a) ** k for k in range(6)], 1), np.arctan(a))
print("atan coefficients", list(c), "max error (rad)", err)
x = np.linspace(0, 1, 200001)
c, err = fit(np.stack([np.sqrt(1 - x) * x**k for k in range(6)], 1), np.pi / 2 - np.arcsin(x))
print("asin coefficients", list(c), "max error (rad)", err)
