"""Numba kernels of the change's error model (:mod:`terralod.change.uncertainty`). Pure functions on arrays.

:func:`spherical_sum` is scikit-gstat's ``skgstat.models.spherical`` (itself a numba function of one lag)
summed over models as xdem's ``fit_sum_model_variogram`` sums them, written with the very same expression
so that it compiles to the same arithmetic: the values, hence the least-squares fit built on them, are bit
for bit xdem's (tests/test_change_uncertainty.py), but all lags are evaluated in one call instead of one
Python call per lag and model (which was most of the fit's time).
"""

from __future__ import annotations

import numpy as np

from terralod.kernels import jit


@jit
def spherical_sum(h, params):
    """Σ_k spherical(h, r_k, c_k) at every lag ``h`` (metres) for ``params`` = (r_0, c_0, r_1, c_1, ...):
    c (1.5 h/r - 0.5 (h/r)³) up to the range r, c beyond it (no nugget)."""
    out = np.empty(h.shape[0], np.float64)
    for k in range(h.shape[0]):
        fn = 0.0
        for i in range(0, params.shape[0] - 1, 2):
            r = params[i]
            c0 = params[i + 1]
            b = 0.0
            a = r / 1.0
            hk = h[k]
            if hk <= r:
                v = b + c0 * ((1.5 * (hk / a)) - (0.5 * ((hk / a) ** 3.0)))
            else:
                v = b + c0
            fn += v
        out[k] = fn
    return out
