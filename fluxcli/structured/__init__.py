"""Structured-light surface capture: projectors, patterns, decoding, triangulation, meshing.

Science only (arrays in, arrays out; no config, no paths, no printing):

- :mod:`.projector`: the pinhole-plus-radial-distortion projector and what shows a pattern;
- :mod:`.patterns`: Gray code + N-step phase-shift patterns and their per-pixel decoding;
- :mod:`.render`: what the simulated camera sees while a projector lights the true surface;
- :mod:`.triangulate`: camera ray x projector column, all views and projectors merged;
- :mod:`.scan`: one projector's scan end to end, merged points, and the decoding per camera view;
- :mod:`.mesh`: points to a closed triangle surface, and distances to a reference surface;
- :mod:`.simulated_rig`: the paper's rig, simulated stand-alone (``make structured-light``).
"""
