"""Edge gradients by the boundary integral: the exact derivative of box-filtered pixels.

A pixel's value is the mean of the radiance f over its box, I = integral_pixel f(x) dx (a
pixel has area 1 in pixel units). Where f jumps along a curve that moves with a parameter
theta (an object's outline, a crease of a flat-shaded mesh), the derivative has two parts
(Reynolds transport):

    dI/dtheta = integral_pixel df/dtheta dx  +  integral_(curves in pixel) (f_- - f_+) v_n ds

The first, the *interior* term, is what the tape already gives (shading differentiated at
fixed visibility, one sample standing for its share of the pixel). The second, the
*boundary* term, is computed here: v_n is the curve's velocity along its unit normal n,
f_+ the radiance just on the side n points to, f_- just on the other.

Every discontinuity curve of primary visibility lies on the image of a mesh edge (a
silhouette, an open boundary, a crease or a seam across which the shading jumps) or of a
sphere's outline. Each is written as the zero set of a function e(x; theta) of the image
position that is smooth in theta:

* a mesh edge (v_i, v_j) seen from the eye C: e = d(x) . ((v_i - C) x (v_j - C)), zero on
  the plane through the eye and the edge, linear in the camera direction d(x);
* a sphere (centre c, radius r): e = (oc . d)^2 - |d|^2 (|oc|^2 - r^2), oc = C - c, the
  discriminant of the ray, zero on the outline, positive inside it.

On the zero set, v_n = -(de/dtheta) / |grad_x e|, with n = grad_x e / |grad_x e|. So the
boundary term of a pixel is a sum over quadrature points x_g on the curve's piece inside it:

    sum_g w_g (f_+ - f_-)(x_g) / |grad_x e(x_g)| * de(x_g; theta)/dtheta

and the renderer adds to the image the term ``c_g * (e(x_g; theta) - detach(e(x_g;
theta)))`` (c_g the constant factor): its value is exactly zero, its derivative is the
boundary term, and the tape takes it to every parameter e depends on (vertices, sphere
centres and radii, the camera's position, look-at, up and field of view) in one backward.

Which parts of an edge are visible, and what lies on either side, is not decided here by
geometry: f_+ and f_- are the radiance seen by two camera rays through x_g +- epsilon n,
shaded as any camera ray (``DirectRadiance``). Where the edge is hidden behind another surface
both rays see that surface and f_+ - f_- vanishes; where a flat-shaded mesh folds, the two
faces' colours differ; where the shading is smooth across an edge the difference is zero.
Every edge of every mesh is therefore a candidate; only the points of edges seen from
behind their own closed surface cost rays they did not need.

The curves are cut at pixel borders (``pixel_pieces``): within a pixel a mesh edge's image
is a straight segment and f_+ - f_- varies smoothly along it, so a fixed Gauss-Legendre
rule integrates it (``GAUSS_POINTS`` per piece). A sphere's outline is a conic: it is
followed as a polyline of short chords, and each quadrature point is moved onto the conic.

The lines where two surfaces pass through each other (the teapot's spout entering its
body) are curves too: the segment two crossing triangles share, with the edge function of
the line where their planes meet (``crossing_segments``); and where a triangle passes
through a sphere, the arc of the circle its plane cuts from the sphere that lies inside
the triangle (``sphere_cut_curves``, followed by chords as an outline is). The points of
outlines and of these arcs are tested for visibility as mesh edges' are (an occlusion ray
to the point where the curve lies; for an arc, also the sphere's far half), before the
rays either side are compared: where a triangle seems to emerge from a sphere the arc is
tangent to the outline, and within EPSILON of each other the rays alone cannot tell which
of the two is seen. Shadow borders (secondary visibility) are curves of the same term
(``shadow_tracing``, ``shadow_border``). Edges seen in mirrors are not included.

The package, one job per module:

* ``curves``: what a curve kind is (``CurveKind``: its curves as segments, its points'
  factors, its edge function on the tape) and what the kinds are handed (``View``);
* ``mesh_edge`` (``MeshEdge``), ``crossing`` (``SurfaceCrossing``), ``sphere``
  (``SphereOutline``, ``SphereCut``): the kinds of primary visibility; ``shadow_tracing``
  (finding the shadow borders) and ``shadow_border`` (their edge function): the shadow
  borders, a kind (``ShadowBorder``: its points moved onto the borders by one pass of
  ``minidiff.compile`` per light);
* ``pixels``: curves cut into pixel pieces, quadrature points on them (Numba);
  ``kind_points``: the points dealt back to their kinds;
* ``occlusion``: which curve points the camera sees (``Occluders``, ``hidden_points``);
* ``radiance``: f_+ and f_- (``SideRadiance``; the direct renderer's ``DirectRadiance``);
* ``term``: the loop over the kinds (``boundary_points``), the term on the tape
  (``boundary_term``), both for one render (``add_curve_terms``).

``render.edges.terms`` lists the direct renderer's kinds; ``render.path.boundary.primary`` hands the
same term its own ``SideRadiance`` (path-traced) and the kinds of primary visibility.
"""

from render.edges.boundary.crossing import SurfaceCrossing, crossing_segments, global_welded
from render.edges.boundary.curves import CurveKind, CurvePoints, Curves, OnCurves, View
from render.edges.boundary.mesh_edge import MeshEdge, continuous_creases, edge_sides_kernel
from render.edges.boundary.occlusion import Occluders, hidden_points
from render.edges.boundary.pixels import pixel_order, pixel_pieces, split_at_crossings
from render.edges.boundary.radiance import (
    EPSILON,
    DirectRadiance,
    SideRadiance,
    seen_through,
)
from render.edges.boundary.sphere import SphereCut, SphereOutline, sphere_cut_curves
from render.edges.boundary.term import add_curve_terms, boundary_points, boundary_term

__all__ = [
    "EPSILON",
    "CurveKind",
    "CurvePoints",
    "Curves",
    "DirectRadiance",
    "MeshEdge",
    "Occluders",
    "OnCurves",
    "SideRadiance",
    "SphereCut",
    "SphereOutline",
    "SurfaceCrossing",
    "View",
    "add_curve_terms",
    "boundary_points",
    "boundary_term",
    "continuous_creases",
    "crossing_segments",
    "edge_sides_kernel",
    "global_welded",
    "hidden_points",
    "pixel_order",
    "pixel_pieces",
    "seen_through",
    "sphere_cut_curves",
    "split_at_crossings",
]
