"""Stage 1, scans: profiles assembled into sweeps, the plate's pose, old marks.

Stage 1, scans: laser-line profiles assembled into sweeps (live, streamed through TF, or from a bag),
the plate's pose, old marks.
"""
