"""Calibration fitting: six-position calibration, thermal polynomial, RBF networks, compensation.

Public API (what the CLI, the sequencer and the store use)::

    from labrunner.calibration import FitOptions, fit_campaign, compensate, load_model

    result = fit_campaign(frame, FitOptions(), provenance={"source": "..."}, progress=print)
    result.to_dict()            # JSON-ready: provenance, data summary, models, evaluation
    result.polynomial           # PolyModel: b(T), S(T) per triad, with uncertainties
    result.rbf                  # RbfModel: the exported network variant (default "hybrid")
    result.not_fitted           # sentences: what the data cannot support
    compensate(model, y, temp)  # Eq. 11 on (N, 6) outputs -> Compensated(values, extrapolated)
    save_model(model, path) / load_model(path)     # model JSON
    write_c_header(path, result.polynomial, result.rbf)

`frame` is a campaign frame with the campaign-CSV columns (`labrunner.campaign_csv`,
`labrunner.data_source.load_campaign_data`). Steps inside `fit_campaign`:

1. `records`       rows -> records (steady run/orientation/rate, a soak or a slow ramp) -> temperature steps
                   (soaks, or bins of continuous ramps)
2. `six_position`  Eq. 2-3 per temperature step, with covariance from the residuals
3. `thermal_poly`  Eq. 4-5: joint one-stage fit (default) or the paper's two-stage fit; order
                   fixed or chosen by cross-validation; temperature range kept for extrapolation flags;
                   bias and S fitted in combination where no axis is seen both up and down
4. `rbf`, `rbf_model`  Eq. 8-10: Gaussian networks, regularised OLS forward selection with GCV,
                   trained on record means; variants paper / triad / hybrid
5. `compensation`  Eq. 11, vectorised; `gain`: every model's Jacobian against the fitted scale (export gate)
6. `evaluation`    held-out errors (random 20 %, between/beyond temperatures, between rates, time blocks),
                   `px4_reference` (PX4's method as a reference row), `ins` (the paper's INS test)
7. `export`, `report`, `command`  model files, C header, tables, `labrunner fit`; `apply`: `labrunner compensate`
"""

from .compensation import Compensated, compensate, compensate_frame
from .export import c_header, load_model, save_model, write_c_header
from .fit import FitOptions, FitResult, fit_campaign
from .rbf_model import RbfModel, RbfOptions
from .records import RecordOptions
from .thermal_poly import PolyModel, TriadPoly

__all__ = [
    "Compensated", "FitOptions", "FitResult", "PolyModel", "RbfModel", "RbfOptions", "RecordOptions", "TriadPoly",
    "c_header", "compensate", "compensate_frame", "fit_campaign", "load_model", "save_model", "write_c_header",
]
