"""Photon Monte Carlo in a homogeneous turbid medium bounded by an analytic shape (box,
slab, cylinder) in air: MCML-style transport (Wang & Jacques 1995), every escaping photon
recorded with its exit point, direction in air and weight.  Arrays and numbers only."""
