"""Calibration science: grid detection, the thin-lens camera fit, mirrors, radiometry (arrays in, numbers out)."""
