"""Stage 0, the head: nominal kinematics, the physical model, its effects, the config file.

Stage 0, the head: nominal kinematics, the physical ray-trace model and its named effects, the head
configuration file.
"""
