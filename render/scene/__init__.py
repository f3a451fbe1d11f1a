"""Step 0, the description: scenes, materials, the camera model, mesh and image files, the
teapot, and the cache that remembers what was computed from a scene's values."""
