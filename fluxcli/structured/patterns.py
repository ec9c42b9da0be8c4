"""Gray code + N-step phase-shift patterns along the projector's columns, and their decoding.

The sequence (:func:`column_patterns`): one full-white and one black frame (the shadow
mask and the albedo), then ``n_gray`` Gray-code bit frames each followed by its inverse
(a bit is read by comparing a frame with its inverse, which needs no threshold), then
``n_steps`` sinusoids of period ``period_px`` shifted by ``2 pi k / n_steps``.

The Gray code counts quarter periods: ``g = floor(4 u / period_px)``.  The wrapped phase
gives the column within a period to a small fraction of a pixel; the Gray code picks the
period.  Because the code resolves a quarter period, the unwrapping tolerates a Gray
error of one code cell at a cell boundary (the case that makes naive period codes
jump by a whole period at period edges).

Gamma: an N-step phase shift is blind to the harmonics 2..N-2 of the fringe, which a
panel gamma creates; with ``n_steps >= 8`` a gamma of 2.2 leaves a phase error below
1e-3 period (measured in ``tests/test_structured.py``).  Patterns can also be pre-
compensated (``gamma=``) when the projector's gamma is known.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["PatternSet", "column_patterns", "Decoded", "decode"]


@dataclass(frozen=True)
class PatternSet:
    """The pattern frames (``[n, height_px, width_px]`` in [0, 1]) and how they were made."""

    frames: np.ndarray
    period_px: float
    n_steps: int
    n_gray: int

    @property
    def labels(self) -> list[str]:
        out = ["white", "black"]
        for b in range(self.n_gray):
            out += [f"gray{b}", f"gray{b}-inverse"]
        return out + [f"phase{k}" for k in range(self.n_steps)]


def _gray(n: np.ndarray) -> np.ndarray:
    return n ^ (n >> 1)


def _gray_to_binary(g: np.ndarray) -> np.ndarray:
    b = g.copy()
    shift = 1
    while True:
        s = b >> shift
        if not np.any(s):
            return b
        b ^= s
        shift <<= 1


def column_patterns(width_px: int, height_px: int, *, period_px: float = 16.0, n_steps: int = 8,
                    gamma: float = 1.0) -> PatternSet:
    """The pattern sequence coding each projector column (see the module docstring).

    Parameters
    ----------
    width_px, height_px : the projector's panel (pixels).
    period_px : fringe period of the phase-shift patterns (projector pixels), a multiple of 4.
    n_steps : phase steps (>= 3).
    gamma : the panel's gamma to pre-compensate (values are raised to ``1/gamma``); 1 = none.
    """
    if n_steps < 3:
        raise ValueError("n_steps must be at least 3")
    if period_px % 4:
        raise ValueError("period_px must be a multiple of 4 (the Gray code counts quarter periods)")
    u = np.arange(width_px) + 0.5  # column centres
    cells = int(np.ceil(4 * width_px / period_px))
    n_gray = max(1, int(np.ceil(np.log2(cells))))
    g = _gray(np.floor(4 * u / period_px).astype(np.int64))
    rows = [np.ones(width_px), np.zeros(width_px)]
    for b in range(n_gray - 1, -1, -1):
        bit = ((g >> b) & 1).astype(float)
        rows += [bit, 1 - bit]
    for k in range(n_steps):
        rows.append(0.5 + 0.5 * np.cos(2 * np.pi * u / period_px - 2 * np.pi * k / n_steps))
    frames = np.stack(rows) ** (1.0 / gamma)
    return PatternSet(np.repeat(frames[:, None, :], height_px, axis=1), float(period_px), int(n_steps), n_gray)


@dataclass(frozen=True)
class Decoded:
    """Per camera pixel: the projector column and what it rests on (arrays ``[ny, nx]``).

    ``column_px`` is the continuous projector column u (nan where masked); ``wrapped_phase``
    in [0, 2 pi); ``modulation`` and ``white``/``black`` in the frames' units; ``lit`` the
    shadow mask (white - black above ``min_contrast``); ``valid`` every mask passed."""

    column_px: np.ndarray
    wrapped_phase: np.ndarray
    modulation: np.ndarray
    white: np.ndarray
    black: np.ndarray
    lit: np.ndarray
    modulated: np.ndarray
    smooth: np.ndarray
    valid: np.ndarray
    # share of the lit, modulated pixels whose Gray cell and phase disagree by more than a quarter
    # period: ~0 for frames in order (0.000 on the sample rig), ~0.5 with a Gray bit and its
    # inverse swapped or the phase steps reversed, 0.23 with a blank Gray frame
    disagreement: float = float("nan")


def decode(frames: np.ndarray, patterns: PatternSet, *, min_contrast: float, min_modulation_fraction: float = 0.25,
           width_px: int | None = None, max_column_jump_px: float | None = None) -> Decoded:
    """Decode camera frames ``[n, ny, nx]`` (in the order of ``patterns.frames``) to projector columns.

    Parameters
    ----------
    frames : the camera's images (photons or bias-subtracted counts), one per pattern.
    patterns : what was shown.
    min_contrast : a pixel is lit when white - black exceeds this (frames' units): the shadow mask.
    min_modulation_fraction : the sinusoid's amplitude must be at least this fraction of
        (white - black) / 2 (low modulation: blur across fringes, interreflections, noise).
    width_px : the panel width; columns outside ``[0, width_px)`` are masked.
    max_column_jump_px : largest second difference of the column between 4-neighbours
        (projector pixels); default a quarter period; ``inf`` turns the edge mask off.
    """
    f = np.asarray(frames, float)
    n_expected = 2 + 2 * patterns.n_gray + patterns.n_steps
    if len(f) != n_expected:
        raise ValueError(f"{len(f)} frames given, the pattern set has {n_expected}")
    white, black = f[0], f[1]
    g = np.zeros(white.shape, np.int64)
    for b in range(patterns.n_gray):
        g = (g << 1) | (f[2 + 2 * b] > f[3 + 2 * b])
    cell = _gray_to_binary(g)
    ph = f[2 + 2 * patterns.n_gray:]
    k = np.arange(patterns.n_steps)
    S = np.tensordot(np.sin(2 * np.pi * k / patterns.n_steps), ph, axes=1)
    Cc = np.tensordot(np.cos(2 * np.pi * k / patterns.n_steps), ph, axes=1)
    wrapped = np.mod(np.arctan2(S, Cc), 2 * np.pi)
    modulation = 2.0 / patterns.n_steps * np.hypot(S, Cc)
    P = patterns.period_px
    fine = wrapped / (2 * np.pi) * P  # u modulo the period (phase 2 pi u / P at column centre u)
    coarse = (cell + 0.5) * P / 4
    m = np.round((coarse - fine) / P)
    column = m * P + fine
    contrast = white - black
    lit = contrast > min_contrast
    modulated = modulation > min_modulation_fraction * 0.5 * np.maximum(contrast, 0)
    valid = lit & modulated & np.isfinite(column)
    if width_px is not None:
        valid &= (column >= 0) & (column < width_px)
    jump = P / 4 if max_column_jump_px is None else max_column_jump_px
    col = np.where(valid, column, np.nan)
    pad = np.pad(col, 1, constant_values=np.nan)
    smooth = np.ones(col.shape, bool)
    if np.isfinite(jump):
        with np.errstate(invalid="ignore"):  # second differences: a slope is smooth, a step is not
            smooth = ((np.abs(pad[:-2, 1:-1] - 2 * col + pad[2:, 1:-1]) <= jump)
                      & (np.abs(pad[1:-1, :-2] - 2 * col + pad[1:-1, 2:]) <= jump))
    valid &= smooth
    seen = lit & modulated & np.isfinite(column)
    disagreement = float(np.mean(np.abs(coarse - column)[seen] > P / 4)) if seen.any() else float("nan")
    return Decoded(np.where(valid, column, np.nan), wrapped, modulation, white, black, lit, modulated, smooth, valid,
                   disagreement)
