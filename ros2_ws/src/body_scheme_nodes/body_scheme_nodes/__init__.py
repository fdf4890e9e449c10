"""Thin rclpy nodes around body_scheme_core. All message mapping lives in :mod:`body_scheme_nodes.conversions`."""
