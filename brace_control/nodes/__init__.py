"""Thin rclpy wrappers: parameters, topics, services, timers. No math here.

Every node pins numpy's BLAS / OpenMP pools to one thread (unless the user set them): the
CAN driver's SYNC thread shares two cores with the nodes, and a BLAS pool spinning on both
cores for a small matrix would take them from it. Set before numpy is imported by any
node module (this package is imported first).

:data:`NODE_NAMES` is the one list of the nodes of a device: ``brace-bringup``, the launch
file, ``setup.py``'s entry points (checked by ``test/test_package_structure.py``), the colcon
test and the README all follow it.
"""
import os as _os

#: the nodes of a device, in data-flow order (each is ``ros2 run brace_control <name>``)
NODE_NAMES = ('trajectory_node', 'ik_node', 'can_driver_node', 'kinetics_node', 'interaction_node')
#: the lifecycle node that owns the bus
DRIVER_NODE = 'can_driver_node'

for _var in ('OPENBLAS_NUM_THREADS', 'OMP_NUM_THREADS', 'MKL_NUM_THREADS', 'BLIS_NUM_THREADS'):
    _os.environ.setdefault(_var, '1')
