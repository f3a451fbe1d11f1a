"""The path integrator's boundary terms: primary visibility's (``primary``: the boundary
integral of ``render.edges`` with path-traced jumps) and secondary visibility's
(``secondary``: soft shadows, lights' shadows, indirect occlusion), with the silhouettes
seen from a point and how a point on them is drawn (``silhouettes``)."""
