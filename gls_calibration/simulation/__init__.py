"""The simulated cell: truth model of the head, the plate and its marks, the laser-line scanner."""
