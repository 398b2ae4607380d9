"""Model files: JSON (both models, reloadable) and a C header for a microcontroller.

The header is self-contained C99: the coefficient tables, the network tables and small
inline functions that compensate one sample,

    int <prefix>poly_compensate(const lr_real y[6], lr_real temp_c, lr_real u[6]);
    int <prefix>rbf_compensate(const lr_real y[6], lr_real temp_c, lr_real u[6]);

y and u are [ax ay az (g), gx gy gz (deg/s)]; both return 1 when the sample lies outside
the data the model was fitted to (extrapolation), else 0. `lr_real` is float unless
LR_USE_DOUBLE is defined before the include.

A model fitted at the lag-corrected temperature (`thermal_lag_fit.TemperatureFilter`) carries its filter:
`temperature_filter` in the JSON model, and in the header a first-order filter state with
`<prefix>temp_filter_init` and `<prefix>temp_filter_update` whose output is the temp_c to pass.
A model fitted per hysteresis branch (`branch_fit.BranchModel`) carries `branch_state`, and the header a
branch state (`<prefix>branch_init`, `<prefix>branch_update`: the filtered dT/dt against its threshold) and
`<prefix>branch_correct`, whose output is the y to pass.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from .branch_fit import BranchModel
from .rbf_model import RbfModel
from .thermal_lag_fit import TemperatureFilter
from .thermal_poly import PolyModel, TriadPoly

FORMAT = "labrunner-calibration-model/1"


def model_to_json(model: PolyModel | RbfModel, provenance: dict[str, Any] | None = None,
                  temperature_filter: TemperatureFilter | None = None,
                  branch: BranchModel | None = None) -> dict[str, Any]:
    from .fit import json_clean

    d = model.to_dict()
    if temperature_filter is not None:
        d["temperature_filter"] = temperature_filter.to_dict()
    if branch is not None:
        d["branch_state"] = branch.to_dict()
    return json_clean({"format": FORMAT, "provenance": provenance or {}, "model": d})


def save_model(model: PolyModel | RbfModel, path: str | Path, provenance: dict[str, Any] | None = None,
               temperature_filter: TemperatureFilter | None = None, branch: BranchModel | None = None) -> None:
    Path(path).write_text(json.dumps(model_to_json(model, provenance, temperature_filter, branch), indent=1,
                                     allow_nan=False))


def filter_from_dict(d: dict[str, Any]) -> TemperatureFilter | None:
    """The temperature filter a model dict carries (`temperature_filter`), or None."""
    f = d.get("temperature_filter")
    return None if f is None else TemperatureFilter.from_dict(f)


def load_model(path: str | Path) -> PolyModel | RbfModel:
    """Read a model written by `save_model` (or the `models` entries of `labrunner fit --json`)."""
    data = json.loads(Path(path).read_text())
    return model_from_dict(data.get("model", data))


def model_from_dict(d: dict[str, Any]) -> PolyModel | RbfModel:
    kind = d.get("kind")
    if kind == "polynomial":
        return PolyModel.from_dict(d)
    if kind == "rbf":
        return RbfModel.from_dict(d)
    raise ValueError(f"not a labrunner calibration model (kind {kind!r})")


# --- C header ------------------------------------------------------------------------


def _num(v: float) -> str:
    v = float(v)
    if not np.isfinite(v):
        raise ValueError("cannot export a non-finite number to C")
    return repr(v) if v != int(v) or abs(v) >= 1e15 else f"{v:.1f}"


def _array(values: np.ndarray, per_line: int = 6) -> str:
    flat = [_num(v) for v in np.asarray(values, dtype=float).ravel()]
    if not flat:
        return "{0}"
    lines = [", ".join(flat[i:i + per_line]) for i in range(0, len(flat), per_line)]
    return "{\n    " + ",\n    ".join(lines) + "\n}"


_COMMON = r"""
#include <math.h>

#ifdef LR_USE_DOUBLE
typedef double lr_real;
#define LR_EXP(x) exp(x)
#define LR_EXPM1(x) expm1(x)
#else
typedef float lr_real;
#define LR_EXP(x) expf(x)
#define LR_EXPM1(x) expm1f(x)
#endif

#ifndef LR_CALIBRATION_COMMON
#define LR_CALIBRATION_COMMON
/* One Gaussian RBF network: out = sum_j w_j exp(-sum_d (z_d - c_jd)^2 / (2 r_d^2)),
   z = (x - offset) / scale. */
typedef struct {
    int dim, n;
    const lr_real *centres;  /* n x dim, normalised */
    const lr_real *width;    /* dim */
    const lr_real *weights;  /* n */
    const lr_real *offset, *scale;   /* dim: input normalisation */
    const lr_real *in_min, *in_max;  /* dim: training input range (raw units) */
} lr_rbf_net;

static inline lr_real lr_rbf_eval(const lr_rbf_net *net, const lr_real *x, lr_real margin, int *outside)
{
    lr_real z[8];
    lr_real out = 0;
    int d, j;
    for (d = 0; d < net->dim; ++d) {
        lr_real span = (net->in_max[d] - net->in_min[d]) * margin;
        if (x[d] < net->in_min[d] - span || x[d] > net->in_max[d] + span) *outside = 1;
        z[d] = (x[d] - net->offset[d]) / net->scale[d] / net->width[d];
    }
    for (j = 0; j < net->n; ++j) {
        lr_real e = 0;
        for (d = 0; d < net->dim; ++d) {
            lr_real t = z[d] - net->centres[j * net->dim + d] / net->width[d];
            e += t * t;
        }
        out += net->weights[j] * LR_EXP(-0.5f * e);
    }
    return out;
}

/* Polynomial triad: solve (I + S(T)) u = y - b(T), coefficients of (T - t_ref)^k, k = 0..order. */
static inline void lr_poly_triad(const lr_real *bias, const lr_real *scale, int order, lr_real t_ref,
                                 const lr_real y[3], lr_real temp_c, lr_real u[3])
{
    lr_real tau = temp_c - t_ref, a[9], r[3], c00, c01, c02, det;
    int i, k;
    for (i = 0; i < 3; ++i) {
        lr_real b = 0;
        for (k = order; k >= 0; --k) b = b * tau + bias[i * (order + 1) + k];
        r[i] = y[i] - b;
    }
    for (i = 0; i < 9; ++i) {
        lr_real s = 0;
        for (k = order; k >= 0; --k) s = s * tau + scale[i * (order + 1) + k];
        a[i] = s + ((i % 4 == 0) ? 1 : 0);
    }
    c00 = a[4] * a[8] - a[5] * a[7];
    c01 = a[5] * a[6] - a[3] * a[8];
    c02 = a[3] * a[7] - a[4] * a[6];
    det = a[0] * c00 + a[1] * c01 + a[2] * c02;
    u[0] = (c00 * r[0] + (a[2] * a[7] - a[1] * a[8]) * r[1] + (a[1] * a[5] - a[2] * a[4]) * r[2]) / det;
    u[1] = (c01 * r[0] + (a[0] * a[8] - a[2] * a[6]) * r[1] + (a[2] * a[3] - a[0] * a[5]) * r[2]) / det;
    u[2] = (c02 * r[0] + (a[1] * a[6] - a[0] * a[7]) * r[1] + (a[0] * a[4] - a[1] * a[3]) * r[2]) / det;
}
#endif /* LR_CALIBRATION_COMMON */
"""


def _poly_tables(p: str, name: str, tp: TriadPoly) -> list[str]:
    m = tp.order + 1
    return [
        f"#define {p.upper()}{name.upper()}_ORDER {tp.order}",
        f"static const lr_real {p}{name}_t_ref_c = {_num(tp.t_ref_c)};",
        f"/* bias[i][k]: axis i, coefficient of (T - t_ref)^k ({'g' if name == 'accel' else 'deg/s'}) */",
        f"static const lr_real {p}{name}_bias[3 * {m}] = {_array(tp.bias, m)};",
        "/* scale[i][j][k]: S_ij (scale-factor error on the diagonal, misalignment off it) */",
        f"static const lr_real {p}{name}_scale[9 * {m}] = {_array(tp.scale, m)};",
    ]


def _poly_section(p: str, model: PolyModel) -> list[str]:
    out = ["/* ---- polynomial thermal model ---- */"]
    out += _poly_tables(p, "accel", model.accel) + _poly_tables(p, "gyro", model.gyro)
    out += [
        f"static const lr_real {p}poly_t_min_c = {_num(model.t_min_c)}, {p}poly_t_max_c = {_num(model.t_max_c)};",
        "",
        f"static inline int {p}poly_compensate(const lr_real y[6], lr_real temp_c, lr_real u[6])",
        "{",
        f"    lr_poly_triad({p}accel_bias, {p}accel_scale, {p.upper()}ACCEL_ORDER, {p}accel_t_ref_c, y, temp_c, u);",
        f"    lr_poly_triad({p}gyro_bias, {p}gyro_scale, {p.upper()}GYRO_ORDER, {p}gyro_t_ref_c,",
        "                  y + 3, temp_c, u + 3);",
        f"    return temp_c < {p}poly_t_min_c || temp_c > {p}poly_t_max_c;",
        "}",
    ]
    return out


def _rbf_section(p: str, model: RbfModel) -> list[str]:
    from .triads import CHANNELS

    out = [f"/* ---- RBF networks (variant: {model.variant}) ---- */"]
    if model.base is not None:
        out += _poly_section(p + "base_", model.base)
    names = []
    for ch, net in zip(CHANNELS, model.networks):
        n = f"{p}net_{ch}"
        names.append(n)
        dim = net.in_offset.size
        cnt = max(net.n_centres, 1)
        centres = net.centres if net.n_centres else np.zeros((1, dim))
        weights = net.weights if net.n_centres else np.zeros(1)
        out += [
            f"/* {ch}: {net.n_centres} centres, inputs: {', '.join(model.to_dict()['inputs'][ch])} */",
            f"static const lr_real {n}_centres[{cnt * dim}] = {_array(centres, dim)};",
            f"static const lr_real {n}_width[{dim}] = {_array(net.width)};",
            f"static const lr_real {n}_weights[{cnt}] = {_array(weights)};",
            f"static const lr_real {n}_offset[{dim}] = {_array(net.in_offset)};",
            f"static const lr_real {n}_scale[{dim}] = {_array(net.in_scale)};",
            f"static const lr_real {n}_min[{dim}] = {_array(net.input_min)};",
            f"static const lr_real {n}_max[{dim}] = {_array(net.input_max)};",
            f"static const lr_rbf_net {n} = {{{dim}, {net.n_centres}, {n}_centres, {n}_width, {n}_weights, "
            f"{n}_offset, {n}_scale, {n}_min, {n}_max}};",
        ]
    out += [
        f"static const lr_rbf_net *const {p}nets[6] = {{{', '.join('&' + n for n in names)}}};",
        f"static const lr_real {p}rbf_t_min_c = {_num(model.t_min_c)}, {p}rbf_t_max_c = {_num(model.t_max_c)};",
        "",
        f"static inline int {p}rbf_compensate(const lr_real y[6], lr_real temp_c, lr_real u[6])",
        "{",
        "    lr_real x[4];",
        "    int k, outside = 0;",
    ]
    if model.base is not None:
        out.append(f"    outside = {p}base_poly_compensate(y, temp_c, u);")
    else:
        out += ["    for (k = 0; k < 6; ++k) u[k] = y[k];",
                f"    outside = temp_c < {p}rbf_t_min_c || temp_c > {p}rbf_t_max_c;"]
    out.append("    for (k = 0; k < 6; ++k) {")
    if model.variant == "triad":
        out += ["        int base = k < 3 ? 0 : 3;",
                "        x[0] = y[base]; x[1] = y[base + 1]; x[2] = y[base + 2]; x[3] = temp_c;"]
    elif model.variant == "hybrid":  # bias(T): the temperature is the only input, held at the training edges
        out += [f"        const lr_rbf_net *net = {p}nets[k];",
                "        x[0] = temp_c < net->in_min[0] ? net->in_min[0]"
                " : (temp_c > net->in_max[0] ? net->in_max[0] : temp_c);",
                "        if (temp_c < net->in_min[0] - (net->in_max[0] - net->in_min[0]) * "
                f"{_num(model.input_margin)} || temp_c > net->in_max[0] + (net->in_max[0] - net->in_min[0]) * "
                f"{_num(model.input_margin)}) outside = 1;"]
    else:
        out += ["        x[0] = y[k]; x[1] = temp_c;"]
    out += [f"        u[k] += lr_rbf_eval({p}nets[k], x, {_num(model.input_margin)}, &outside);",
            "    }",
            "    return outside;",
            "}"]
    return out


def _filter_section(p: str, f: TemperatureFilter) -> list[str]:
    # y' = x + alpha (y - x_prev) - beta (x - x_prev): the exact first-order-hold step of
    # dy/dt = (x - y)/tau (x linear over the sample), as labrunner.imu.recursions.first_order_lag; written
    # in differences so that single precision keeps the small lag.
    return [
        "/* ---- temperature filter: the sensing element lags the temperature sensor ----",
        f" * The models take the element temperature, the sensor's through dy/dt = (x - y) / tau, tau = {f.tau_s:g} s.",
        f" * Call {p}temp_filter_init at power-on with the first temperature, then {p}temp_filter_update with every",
        f" * sample's temperature (every {f.sample_period_s:g} s; {p}temp_filter_update_dt for another interval), and",
        " * pass what it returns as temp_c to the compensation functions. */",
        f"#define {p.upper()}TEMP_FILTER 1",
        f"static const lr_real {p}temp_filter_tau_s = {_num(f.tau_s)};",
        f"static const lr_real {p}temp_filter_period_s = {_num(f.sample_period_s)};",
        f"static const lr_real {p}temp_filter_alpha = {_num(f.alpha)};  /* exp(-period / tau) */",
        f"static const lr_real {p}temp_filter_beta = {_num(f.beta)};  /* (1 - alpha) tau / period */",
        f"typedef struct {{ lr_real y, x_prev; }} {p}temp_filter;",
        "",
        f"static inline void {p}temp_filter_init({p}temp_filter *f, lr_real temp_c)",
        "{",
        "    f->y = temp_c;",
        "    f->x_prev = temp_c;",
        "}",
        "",
        f"static inline lr_real {p}temp_filter_step({p}temp_filter *f, lr_real temp_c, lr_real alpha, lr_real beta)",
        "{",
        "    f->y = temp_c + alpha * (f->y - f->x_prev) - beta * (temp_c - f->x_prev);",
        "    f->x_prev = temp_c;",
        "    return f->y;",
        "}",
        "",
        f"static inline lr_real {p}temp_filter_update({p}temp_filter *f, lr_real temp_c)",
        "{",
        f"    return {p}temp_filter_step(f, temp_c, {p}temp_filter_alpha, {p}temp_filter_beta);",
        "}",
        "",
        f"static inline lr_real {p}temp_filter_update_dt({p}temp_filter *f, lr_real temp_c, lr_real dt_s)",
        "{",
        "    lr_real x, em1;",
        f"    if (dt_s <= 0) return {p}temp_filter_step(f, temp_c, 1, 1);",
        f"    x = dt_s / {p}temp_filter_tau_s;",
        "    em1 = -LR_EXPM1(-x);  /* 1 - alpha */",
        f"    return {p}temp_filter_step(f, temp_c, 1 - em1, em1 / x);",
        "}",
    ]


def c_header(poly: PolyModel | None, rbf: RbfModel | None, prefix: str = "lr_",
             comment: str = "", temperature_filter: TemperatureFilter | None = None,
             branch: BranchModel | None = None) -> str:
    """The C header text for the given models (either may be None)."""
    guard = f"{prefix.upper()}CALIBRATION_H"
    lines = [
        "/* Thermal calibration of a MEMS IMU, generated by labrunner (`labrunner fit --out`).",
        " * y, u: [ax ay az] g, [gx gy gz] deg/s; temp_c: the IMU's temperature sensor.",
        " * Compensation (paper Eq. 11): u = y + dU(y, T) (RBF) or u = (I + S(T))^-1 (y - b(T)) (polynomial).",
        " * Functions return 1 when the sample is outside the fitted range (extrapolation). */",
    ]
    if comment:  # provenance, one item a line
        body = comment.replace("*/", "* /").splitlines()
        lines += ["/* " + body[0]] + [" * " + b for b in body[1:]] + [" */"]
    lines += [f"#ifndef {guard}", f"#define {guard}", _COMMON]
    if temperature_filter is not None:
        lines += _filter_section(prefix, temperature_filter) + [""]
    if branch is not None:
        from .branch_fit import c_section

        lines += c_section(prefix, branch, _num) + [""]
    if poly is not None:
        lines += _poly_section(prefix, poly) + [""]
    if rbf is not None:
        lines += _rbf_section(prefix, rbf) + [""]
    lines += [f"#endif /* {guard} */", ""]
    return "\n".join(lines)


def write_c_header(path: str | Path, poly: PolyModel | None, rbf: RbfModel | None, prefix: str = "lr_",
                   comment: str = "", temperature_filter: TemperatureFilter | None = None,
                   branch: BranchModel | None = None) -> None:
    Path(path).write_text(c_header(poly, rbf, prefix, comment, temperature_filter, branch))
