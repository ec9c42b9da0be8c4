"""Figures of a radiometric calibration: arrays and numbers in, matplotlib figures out.

:func:`ptc_figure` takes the ``/radiometric/ptc`` group of calibration.h5 as it is (an
``h5py.Group``), or any mapping of the same shape (series name -> mapping of arrays), so
the report needs nothing but the artefact.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

__all__ = ["ptc_figure", "sensor_maps_figure"]

_SERIES_STYLE = {"em_gain_off": ("C0", "EM gain off"), "em_gain_on": ("C3", "EM gain on")}


def _value(mapping: Mapping, key: str):
    v = mapping[key]
    return v[()] if hasattr(v, "shape") else v


def ptc_figure(ptc: Mapping, *, electrons_per_count: float | None = None, em_gain: float | None = None,
               read_noise_counts: float | None = None) -> Figure:
    """Photon-transfer curves: temporal variance against mean signal, with the line fits.

    Parameters
    ----------
    ptc : mapping of str to mapping
        Per series (``"em_gain_off"``, ``"em_gain_on"``) the arrays ``mean_counts``
        (counts above bias), ``variance_counts2`` (counts²), ``variance_sigma_counts2``
        (counts², 1 sigma) and the scalars ``slope_counts``, ``intercept_counts2``:
        ``calibration.h5:/radiometric/ptc`` or the same built from ``PTCSeries`` fields.
    electrons_per_count, em_gain, read_noise_counts : float, optional
        Measured values written in the legend (electrons/count, dimensionless, counts).

    Returns
    -------
    matplotlib.figure.Figure
        Log-log axes; one colour per series; dashed lines are the fits
        ``Var = intercept + slope · mean``, dotted the read-noise floor.
    """
    fig = Figure(figsize=(6.4, 4.6), constrained_layout=True)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    lo, hi = np.inf, 0.0
    for name in sorted(ptc):
        s = ptc[name]
        mean = np.asarray(_value(s, "mean_counts"), dtype=float)
        var = np.asarray(_value(s, "variance_counts2"), dtype=float)
        err = np.asarray(_value(s, "variance_sigma_counts2"), dtype=float)
        slope, icpt = float(_value(s, "slope_counts")), float(_value(s, "intercept_counts2"))
        colour, label = _SERIES_STYLE.get(name, (None, name.replace("_", " ")))
        fit = f"slope {slope:.4g}"
        ax.errorbar(mean, var, yerr=err, fmt="o", ms=4, color=colour, label=f"{label}: {fit}")
        positive = mean[mean > 0]
        if positive.size:
            x = np.geomspace(positive.min() / 1.5, positive.max() * 1.5, 100)
            ax.plot(x, icpt + slope * x, "--", color=colour, lw=1)
            lo, hi = min(lo, x[0]), max(hi, x[-1])
    if read_noise_counts is not None and hi > 0:
        ax.axhline(read_noise_counts**2, ls=":", color="0.4", lw=1,
                   label=f"read noise² from bias pairs ({read_noise_counts:.3g} counts rms)")
    notes = []
    if electrons_per_count is not None:
        notes.append(f"K = {electrons_per_count:.4g} e⁻/count")
    if em_gain is not None:
        notes.append(f"G = {em_gain:.4g}")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("mean signal above bias (counts)")
    ax.set_ylabel("variance, var(a − b)/2 (counts²)")
    ax.set_title("Photon transfer" + (": " + ", ".join(notes) if notes else ""))
    ax.legend(loc="upper left", fontsize="small")
    ax.grid(True, which="both", alpha=0.3)
    return fig


def sensor_maps_figure(maps: Mapping) -> Figure:
    """Images of the measured sensor maps side by side.

    Parameters
    ----------
    maps : mapping of str to array (ny, nx)
        Any of ``bias_counts_map`` (counts), ``dark_e_per_s_map`` (electrons/s),
        ``flat_map`` (dimensionless), e.g. ``calibration.h5:/radiometric``; absent or None
        maps are skipped.

    Returns
    -------
    matplotlib.figure.Figure
        One panel per map, colour scale from the 1st to the 99th percentile.
    """
    units = {"bias_counts_map": "bias (counts)", "dark_e_per_s_map": "dark current (e⁻/s)",
             "flat_map": "flat field (relative)"}
    present = [(k, np.asarray(_value(maps, k), dtype=float)) for k in units if k in maps and maps[k] is not None]
    fig = Figure(figsize=(4.0 * max(len(present), 1), 3.6), constrained_layout=True)
    FigureCanvasAgg(fig)
    for i, (name, arr) in enumerate(present):
        ax = fig.add_subplot(1, len(present), i + 1)
        vmin, vmax = np.percentile(arr, [1, 99])
        im = ax.imshow(arr, vmin=vmin, vmax=vmax, cmap="viridis", interpolation="nearest")
        ax.set_title(units[name])
        ax.set_xlabel("column")
        ax.set_ylabel("row")
        fig.colorbar(im, ax=ax, shrink=0.85)
    return fig
