"""labrunner: thermal-calibration campaigns for MEMS IMUs."""

from labrunner.version import __version__

__all__ = ["__version__"]
