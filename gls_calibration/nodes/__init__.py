"""Thin rclpy nodes over the core: parameters, topics and services only.

Importing this package sets the process's allocator options for sweep-sized arrays
(:func:`gls_calibration.ros.allocator.keep_freed_memory`; ``GLS_KEEP_FREED_MEMORY=0`` leaves glibc's
defaults): it must happen before numpy, OpenCV and rclpy start threads of their own, and an
executable imports its package before its module's imports.
"""
from gls_calibration.ros.allocator import keep_freed_memory

keep_freed_memory()
