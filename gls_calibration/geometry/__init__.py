"""Stage 0, the head: nominal kinematics, the physical model, its effects, the config file.

The nominal kinematics, the physical ray-trace model with its named effects, and the head
configuration file.
"""
