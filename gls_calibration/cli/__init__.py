"""Command-line tools: the simulated cell, the operator clients and the discrepancy workflow."""
