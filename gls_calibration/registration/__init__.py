"""Stage 3, registration: centres onto targets, sweep combination, scanner-error separation.

Stage 3, registration: measured centres onto the targets, combination of sweeps and separation of the
scanner's errors.
"""
