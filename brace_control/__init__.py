"""brace_control: ROS 2 control stack for rehabilitation braces on small parallel mechanisms.

The math (:mod:`brace_control.mechanisms`, :mod:`brace_control.trajectory`) never imports
rclpy or CAN; nodes (:mod:`brace_control.nodes`) hold no math.
"""

__version__ = '0.1.0'
