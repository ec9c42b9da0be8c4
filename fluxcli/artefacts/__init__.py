"""The data model: versioned HDF5 artefacts, their kinds, provenance and the T cache.

- :mod:`.kinds`: each artefact kind's schema version, datasets, units (one place);
- :mod:`.atomic`: the one atomic writer (temp file, fsync, rename, umask, stale temps);
- :mod:`.store`: write/open artefacts, provenance (config, geometry, input files), checks;
- :mod:`.pieces`: surfaces and sparse matrices inside artefacts;
- :mod:`.transfer`: T files (the content-addressed T cache) and the transfer index;
- :mod:`.info`: what ``fluxmap info ARTEFACT`` prints;
- :mod:`.provenance`: the set-up an artefact records it was made for;
- one module per kind with a container: :mod:`.simulation`, :mod:`.surface`, :mod:`.tetmesh`,
  :mod:`.capture` (the durable frame-by-frame writer and the readers), :mod:`.calibration`.
"""

from .atomic import atomic_path, clean_stale_temps, write_bytes, write_text
from .kinds import KINDS, SCHEMA_VERSIONS, Dataset, Kind, register
from .pieces import read_csr, read_surface, write_csr, write_surface
from .store import (ArtefactFile, Provenance, cache_key, canonical, check_geometry, file_sha256,
                    geometry_differences, inputs_digest, is_up_to_date, open_artefact, portable_path, put,
                    read_provenance, recorded_seconds, write_artefact)
from . import simulation, surface, tetmesh  # noqa: E402,F401  (each registers its kind on import)

__all__ = [
    "KINDS", "SCHEMA_VERSIONS", "ArtefactFile", "Dataset", "Kind", "Provenance", "atomic_path", "cache_key",
    "canonical", "check_geometry", "clean_stale_temps", "file_sha256", "geometry_differences", "inputs_digest",
    "is_up_to_date", "open_artefact", "portable_path", "put", "recorded_seconds", "read_csr", "read_provenance", "read_surface", "register",
    "write_artefact", "write_bytes", "write_csr", "write_surface", "write_text",
]
