"""labrunner: thermal-calibration campaigns for MEMS IMUs."""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("labrunner")
except PackageNotFoundError:  # running from a source tree that was not installed
    __version__ = "0.0.0+source"
