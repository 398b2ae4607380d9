"""The IMU error model: the one the simulated IMU runs and the one the diagnosis fits.

`baseline.py` is the paper's Eq. 1 with cubic thermal terms; `effects/` holds every
further effect, one class per file, registered by discovery (`effect.py` is their base
class); `model.py` sums them into `ImuModel`, the simulator's error model.

Base layer: the simulator (`labrunner.sims`) and the analysis (`labrunner.discrepancy`,
`labrunner.calibration`) import it; it imports only `labrunner.domain`.
"""
