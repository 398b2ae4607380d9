"""Simulated chamber, rate table and IMU that speak the drivers' protocols."""
