"""Camera and ray geometry: poses and their corrections, scene contraction, per-scene ray spaces."""
