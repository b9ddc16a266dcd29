"""Stage 7, the report of a calibration: Markdown, plots, CSV and JSON."""
