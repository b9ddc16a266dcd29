"""Shared by every stage: validation, statistics, config and atomic files, parameters, timing.

Shared by every stage: input validation, robust statistics, config files, atomic files, parameter records,
time budget.
"""
