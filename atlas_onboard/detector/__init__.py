"""The detector: camera frames in, MarkerData out (the only package, with the simulator's renderer,
that imports OpenCV)."""
