"""Grid encodings, the G²fR level mask, the radiance field, the occupancy grid and the renderer."""
