"""In-situ calibration of the galvanometric laser scanner of a robotic laser cell."""

__version__ = "0.1.0"
