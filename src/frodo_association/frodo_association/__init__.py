"""Association node: ray-segment DP-means clustering of detections into objects, 3D boxes and detection pruning (paper Sec. 5.1, supplement)."""
