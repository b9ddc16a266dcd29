"""Stage 6, the calibrate flow: procedure, outcome, stated accuracy, the calibration record, its file and the store."""
