"""Stage 5, correction: corrected targets (off the plane through Q') to mirror angles and focus."""
