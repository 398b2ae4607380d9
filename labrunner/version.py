"""The installed version of labrunner (base layer: anything may import it)."""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("labrunner")
except PackageNotFoundError:  # running from a source tree that was not installed
    __version__ = "0.0.0+source"
