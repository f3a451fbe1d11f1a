"""Step 1, discrete work on plain arrays (no tape): which primitive each ray hits (BVH,
rasteriser), which lights each hit sees (the light's view, the BVH), mesh topology."""
