"""fluxmap: quantitative surface-flux mapping for preclinical optical imaging.

The package is ``fluxcli``; the command is ``fluxmap``.  See README.md.
"""

__version__ = "0.1.0"

from . import _numba_cache

NUMBA_CACHE = _numba_cache.configure()  # before any kernel module imports numba
