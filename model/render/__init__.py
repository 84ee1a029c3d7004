"""Rendering: EWA projection, the differentiable and the fast rasterizer, their input checks, SH colour,
and the float64 reference renderer both are tested against."""
