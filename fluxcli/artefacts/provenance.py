"""What an artefact records it was made for: the set-up (system and subject as configured,
the digest of the surface as built) and the resolved config.

A later stage compares the geometry an artefact records with its own
(:func:`fluxcli.artefacts.check_geometry`); the functions here take the config's parts,
not the config.
"""

from __future__ import annotations

from typing import Any, Callable

from .store import Provenance


def geometry_of(system: Any, subject: Any, emission_key: Callable[[], str] | None = None,
                surface_sha256: str | None = None) -> dict:
    """The set-up an artefact is made for: ``system`` (camera, lens, sensor, apertures, mirrors,
    stage) and ``subject`` (surface, poses, rotation axis) as their config models (or None),
    and the digest of the built surface.  ``emission_key``: gives the key of the subject's
    emission profile (:meth:`fluxcli.optics.emission.Profile.key`); asked only when
    ``subject.emission`` is set and not Lambertian."""
    g = {"system": system.model_dump(mode="json") if system is not None else None,
         "subject": subject.model_dump(mode="json") if subject is not None else None}
    if g["system"] is not None:  # a calibration's 1 sd is not the set-up (reconstruct's error budget reads it)
        g["system"]["camera"].pop("uncertainty", None)
        for mirror in g["system"].get("mirrors") or ():
            mirror.pop("normal_sigma_deg", None)
            mirror.pop("offset_sigma_mm", None)
    if g["subject"] is not None:  # Lambertian (absent or explicit): the digest of before emission profiles
        em = g["subject"].pop("emission", None)
        if em is not None and em.get("model") != "lambertian":
            g["subject"]["emission"] = emission_key()  # a table by its numbers, not its path
    if surface_sha256 is not None:
        g["surface_sha256"] = surface_sha256
    return g


def without_emission(geometry: dict) -> dict:
    """The geometry with no emission model: what a Monte Carlo simulation is made for (its photons
    assume none, so its images serve a reconstruction under any ``subject.emission``)."""
    g = dict(geometry)
    if g.get("subject") is not None:
        g["subject"] = {k: v for k, v in g["subject"].items() if k != "emission"}
    return g


def provenance_of(config_json: dict, geometry: dict) -> Provenance:
    """The provenance of an artefact made from the resolved config ``config_json`` (the model
    dumped by alias, JSON mode) for ``geometry`` (:func:`geometry_of`)."""
    return Provenance(config=config_json, geometry=geometry)
