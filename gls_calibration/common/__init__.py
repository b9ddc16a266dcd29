"""Shared by every stage: input validation, robust statistics, config files, atomic files, parameter records,
time budget.
"""
