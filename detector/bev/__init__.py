"""From image corners to the ground: the calibration-free BEV homography, metric lifting, pictures."""
