"""Step 4, moving edges: silhouettes and shadow edges blended on the tape."""
