"""Step 4, moving edges: silhouettes, creases and shadow edges blended on the tape.

``terms.add_edge_terms`` is the one entry point (the renderer calls it with
``antialias=True``); ``silhouettes`` and ``shadows`` find and blend each kind of pair;
``geometry`` holds what both share (the sample grid, edge functions, crossings, box
coverage).
"""
