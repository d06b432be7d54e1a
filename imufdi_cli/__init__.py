"""imufdi: fault detection and isolation for redundant MEMS IMU arrays, on MCAP logs."""

__version__ = "0.1.0"
