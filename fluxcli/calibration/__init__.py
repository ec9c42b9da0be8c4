"""Calibration science: grid detection, the thin-lens camera fit, mirrors (arrays in, numbers out)."""
