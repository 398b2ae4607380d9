"""The baseline error of one sensor triad: the paper's Eq. 1 with cubic thermal terms.

    e = S(T) u + b(T)

S holds scale-factor errors on its diagonal and misalignment off it, b is the bias, each
element a cubic in (T - T_REF_C). The simulator evaluates it through `TriadModel.error`,
the diagnosis fits it through `baseline_design`: the same coefficients in the same layout.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from labrunner.domain import T_REF_C

POLY_ORDER = 3  # cubic thermal terms: coefficients c0..c3 of (T - T_REF_C)**k
N_COEF = POLY_ORDER + 1


def thermal_powers(temp_c: np.ndarray) -> np.ndarray:
    """(N, 4) matrix of (T - T_REF_C)**k, k = 0..3."""
    tau = np.asarray(temp_c, dtype=float) - T_REF_C
    # Filled in place (the simulator calls this per chunk): the same products as stacking the columns.
    out = np.empty(tau.shape + (N_COEF,))
    out[..., 0] = 1.0
    out[..., 1] = tau
    sq = np.multiply(tau, tau, out=out[..., 2])
    np.multiply(sq, tau, out=out[..., 3])
    return out


def baseline_design(temp_c: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """(N, 16) regressors of one triad's baseline error for one output channel.

    The error of channel i is design @ coef[i], with coef[i] laid out as
    [bias c0..c3, S[i,0] c0..c3, S[i,1] c0..c3, S[i,2] c0..c3]; the design is the
    same for the three channels of a triad.
    """
    p = thermal_powers(temp_c)
    u = np.asarray(reference, dtype=float)
    return np.concatenate([p, p * u[:, 0:1], p * u[:, 1:2], p * u[:, 2:3]], axis=1)


@dataclass
class TriadModel:
    """Thermal error terms of one sensor triad."""

    bias: np.ndarray  # (3, 4): b_i(T) coefficients, sensor units
    scale: np.ndarray  # (3, 3, 4): S_ij(T) coefficients, unitless
    noise_density: float  # white noise, sensor units per sqrt(Hz)

    def __post_init__(self) -> None:
        self.bias = np.asarray(self.bias, dtype=float).reshape(3, N_COEF)
        self.scale = np.asarray(self.scale, dtype=float).reshape(3, 3, N_COEF)

    def coefficients(self) -> np.ndarray:
        """(3, 16) coefficients matching `baseline_design`."""
        return np.concatenate([self.bias, self.scale[:, 0], self.scale[:, 1], self.scale[:, 2]], axis=1)

    @classmethod
    def from_coefficients(cls, coef: np.ndarray, noise_density: float) -> TriadModel:
        coef = np.asarray(coef, dtype=float).reshape(3, 4 * N_COEF)
        scale = np.stack([coef[:, N_COEF * (1 + j): N_COEF * (2 + j)] for j in range(3)], axis=1)
        return cls(bias=coef[:, :N_COEF], scale=scale, noise_density=noise_density)

    def bias_at(self, temp_c: np.ndarray) -> np.ndarray:
        """(N, 3) bias at temperatures."""
        return thermal_powers(temp_c) @ self.bias.T

    def scale_at(self, temp_c: np.ndarray) -> np.ndarray:
        """(N, 3, 3) S(T)."""
        return np.einsum("nk,ijk->nij", thermal_powers(temp_c), self.scale)

    def error(self, temp_c: np.ndarray, reference: np.ndarray) -> np.ndarray:
        """(N, 3) baseline error S(T) u + b(T)."""
        return self.error_at_powers(thermal_powers(temp_c), reference)

    def error_at_powers(self, powers: np.ndarray, reference: np.ndarray) -> np.ndarray:
        """`error` from the temperatures' `thermal_powers` (both triads of a model share them)."""
        u = np.asarray(reference, dtype=float)
        err = powers @ self.bias.T
        term = np.empty_like(err)
        # The axes not zero throughout, in one pass: a broadcast reference (one vector for every sample) by
        # its one row (what any() of each column finds, NaN included).
        rows = u[:1] if u.strides[0] == 0 else u
        used = [bool(v) for v in np.asarray(rows.any(axis=0))] if u.shape[0] else [False] * 3
        for j in range(3):
            # A reference axis that is zero throughout (the force and the table's rate lie along one body
            # axis) adds S[:, j] * 0 = +-0: nothing to an error that is not itself a signed zero.
            if not used[j]:
                continue
            np.matmul(powers, self.scale[:, j, :].T, out=term)
            if u.strides[0] == 0:  # one reference for every sample (a broadcast): times its scalar, the same
                term *= u[0, j]
            else:
                term *= u[:, j: j + 1]
            err += term
        return err
