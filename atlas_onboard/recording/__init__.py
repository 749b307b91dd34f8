"""What a camera saw, on disk: the recording format (frames, their capture stamps, the detections and the
camera's calibration) and the node's recorders. Below both the detector, which replays recordings as a
camera source, and the map builder, which solves the markers' poses from them."""
