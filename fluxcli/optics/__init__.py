"""Thin-lens camera, mirrors, apertures and the transfer-matrix estimators."""
