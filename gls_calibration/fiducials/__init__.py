"""Stage 2, fiducials: the grid of double-ring targets and the measurement of their centres in a scan."""
