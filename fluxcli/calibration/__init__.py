"""Camera calibration: grid detection, camera fit, radiometry."""
