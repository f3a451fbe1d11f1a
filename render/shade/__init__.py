"""Steps 2 and 3, on the tape: surfaces recomputed from the hits, lights and materials,
mirror bounces."""
