"""pybullet arm simulator seen by a fixed camera (issue 4): robots, rendering, babbling, faults, ground truth."""
