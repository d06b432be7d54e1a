"""imufdi: fault detection and isolation for redundant MEMS IMU arrays, on MCAP logs."""

from imufdi_cli._version import __version__

__all__ = ["__version__"]
