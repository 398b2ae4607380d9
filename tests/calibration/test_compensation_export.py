"""Compensation (Eq. 11), model JSON round trip and the C header compiled with gcc."""

from __future__ import annotations

import shutil
import subprocess

import numpy as np
import pytest

from labrunner.calibration import compensate, load_model, save_model, write_c_header
from labrunner.calibration.fit import FitOptions, fit_campaign
from labrunner.calibration.thermal_poly import PolyModel, TriadPoly


def _random_triad(rng, triad, order=3):
    return TriadPoly(triad, order, 25.0, rng.normal(size=(3, order + 1)) * 10.0 ** -np.arange(2, 2 + order + 1),
                     rng.normal(size=(3, 3, order + 1)) * 10.0 ** -np.arange(2, 2 + order + 1),
                     np.zeros((3, order + 1)), np.zeros((3, 3, order + 1)), -20.0, 60.0)


def test_polynomial_compensation_inverts_the_model_exactly():
    rng = np.random.default_rng(0)
    model = PolyModel(_random_triad(rng, "accel"), _random_triad(rng, "gyro"))
    n = 5000
    u = np.concatenate([rng.normal(size=(n, 3)), rng.normal(0, 50, (n, 3))], axis=1)
    temp = rng.uniform(-30, 70, n)
    y = np.empty_like(u)
    for sl, tp in ((slice(0, 3), model.accel), (slice(3, 6), model.gyro)):
        s = tp.scale_at(temp)
        y[:, sl] = u[:, sl] + np.einsum("nij,nj->ni", s, u[:, sl]) + tp.bias_at(temp)
    comp = compensate(model, y, temp)
    assert np.allclose(comp.values, u, atol=1e-10)
    assert np.array_equal(comp.extrapolated, (temp < -20) | (temp > 60))


@pytest.fixture(scope="module")
def fitted(nonlinear_campaign):
    return fit_campaign(nonlinear_campaign, FitOptions(evaluate=False))


def test_json_round_trip_compensates_identically(fitted, tmp_path, nonlinear_campaign):
    y = nonlinear_campaign[["ax_g", "ay_g", "az_g", "gx_dps", "gy_dps", "gz_dps"]].to_numpy()[::13]
    temp = nonlinear_campaign["imu_temp_c"].to_numpy()[::13]
    for name, model in [("poly", fitted.polynomial)] + [(v, m) for v, m in fitted.models.rbf.items()]:
        save_model(model, tmp_path / f"{name}.json", fitted.provenance)
        again = load_model(tmp_path / f"{name}.json")
        a, b = compensate(model, y, temp), compensate(again, y, temp)
        assert np.array_equal(a.values, b.values) and np.array_equal(a.extrapolated, b.extrapolated), name


MAIN_C = r"""
#include <stdio.h>
#include "cal.h"
int main(void) {
    double v[7];
    while (scanf("%lf %lf %lf %lf %lf %lf %lf", &v[0], &v[1], &v[2], &v[3], &v[4], &v[5], &v[6]) == 7) {
        lr_real y[6], up[6], ur[6];
        int k, fp, fr;
        for (k = 0; k < 6; ++k) y[k] = (lr_real)v[k];
        fp = lr_poly_compensate(y, (lr_real)v[6], up);
        fr = lr_rbf_compensate(y, (lr_real)v[6], ur);
        for (k = 0; k < 6; ++k) printf("%.17g ", (double)up[k]);
        for (k = 0; k < 6; ++k) printf("%.17g ", (double)ur[k]);
        printf("%d %d\n", fp, fr);
    }
    return 0;
}
"""


@pytest.mark.skipif(shutil.which("gcc") is None, reason="gcc not available")
@pytest.mark.parametrize("variant", ["paper", "triad", "hybrid"])
def test_c_header_matches_python(fitted, tmp_path, nonlinear_campaign, variant):
    rng = np.random.default_rng(1)
    rows = rng.choice(len(nonlinear_campaign), 400, replace=False)
    y = nonlinear_campaign[["ax_g", "ay_g", "az_g", "gx_dps", "gy_dps", "gz_dps"]].to_numpy()[rows]
    temp = nonlinear_campaign["imu_temp_c"].to_numpy()[rows].copy()
    temp[:10] = 75.0  # beyond the calibrated range: both must flag it
    rbf = fitted.models.rbf[variant]
    write_c_header(tmp_path / "cal.h", fitted.polynomial, rbf, comment="test */ comment")
    (tmp_path / "main.c").write_text(MAIN_C)
    text = "\n".join(" ".join(repr(float(v)) for v in (*r, t)) for r, t in zip(y, temp)) + "\n"
    poly = compensate(fitted.polynomial, y, temp)
    ref = compensate(rbf, y, temp)
    precise = ref.values.copy()
    for k, net in enumerate(rbf.networks):
        base = rbf.base and compensate(rbf.base, y, temp).values[:, k]
        x = rbf.inputs(y, temp, k)
        if rbf.variant == "hybrid":  # bias(T) is held at its edge values beyond the training temperatures
            x = np.clip(x, net.input_min, net.input_max)
        precise[:, k] = (base if rbf.base else y[:, k]) + net.predict(x, precise=True)
    bound = np.array([net.float32_error_bound for net in rbf.networks])
    for flags, tol_poly, tol_rbf in (("-DLR_USE_DOUBLE", 1e-9, 1e-9), ("", 2e-5, None)):
        exe = tmp_path / f"cal{flags or '_float'}"
        subprocess.run(["gcc", "-std=c99", "-O2", "-Wall", "-Wextra", "-Werror", *([flags] if flags else []),
                        "-o", str(exe), str(tmp_path / "main.c"), "-lm"], check=True)
        out = subprocess.run([str(exe)], input=text, capture_output=True, text=True, check=True).stdout
        arr = np.array([[float(x) for x in line.split()] for line in out.strip().splitlines()])
        assert arr.shape == (400, 14)
        scale = np.array([1, 1, 1, 100, 100, 100.0])  # g and deg/s magnitudes
        assert np.all(np.abs(arr[:, :6] - poly.values) <= tol_poly * scale)
        if tol_rbf is not None:
            assert np.all(np.abs(arr[:, 6:12] - precise) <= tol_rbf * scale)
        else:  # float: within the networks' stated single-precision bound plus the float inputs' rounding
            assert np.all(np.abs(arr[:, 6:12] - precise) <= bound + 2e-5 * scale + 1e-6 * np.abs(precise))
        assert np.array_equal(arr[:, 12].astype(bool), poly.extrapolated)
        assert np.array_equal(arr[:, 13].astype(bool), ref.extrapolated)
        assert arr[:10, 12].all() and arr[:10, 13].all()
