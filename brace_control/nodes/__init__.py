"""Thin rclpy wrappers: parameters, topics, services, timers. No math here.

Every node pins numpy's BLAS / OpenMP pools to one thread (unless the user set them): the
CAN driver's SYNC thread shares two cores with the nodes, and a BLAS pool spinning on both
cores for a small matrix would take them from it. Set before numpy is imported by any
node module (this package is imported first).
"""
import os as _os

for _var in ('OPENBLAS_NUM_THREADS', 'OMP_NUM_THREADS', 'MKL_NUM_THREADS', 'BLIS_NUM_THREADS'):
    _os.environ.setdefault(_var, '1')
