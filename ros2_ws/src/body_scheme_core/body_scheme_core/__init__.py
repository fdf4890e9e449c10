"""body_scheme_core: learning and maintaining a robot's body scheme from self-observation.

A plain Python implementation of Sturm, Plagemann and Burgard, "Adaptive Body Scheme Models for Robust Robotic
Manipulation", RSS 2008. No ROS imports: the ROS 2 nodes in ``body_scheme_nodes`` wrap this package.
"""

__version__ = "0.1.0"
