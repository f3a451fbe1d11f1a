"""The shadow borders' old home, kept while ``render.edges.terms`` moves to the curve kinds:
finding them is ``render.edges.boundary.shadow_tracing``, their edge function and term
``render.edges.boundary.shadow_border``."""

from render.edges.boundary.shadow_border import shadow_points, shadow_term
from render.edges.boundary.shadow_tracing import border_chords

__all__ = ["border_chords", "shadow_points", "shadow_term"]
