"""Thin rclpy nodes over the core: parameters, topics and services only."""
