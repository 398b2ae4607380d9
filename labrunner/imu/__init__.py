"""The IMU error model: the one the simulated IMU runs and the one the diagnosis fits.

Base layer: the simulator (`labrunner.sims`) and the analysis (`labrunner.discrepancy`,
`labrunner.calibration`) import it; it imports only `labrunner.domain`.
"""
