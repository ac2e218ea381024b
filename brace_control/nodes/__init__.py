"""Thin rclpy wrappers: parameters, topics, services, timers. No math here."""
