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


def _started_as_a_node() -> bool:
    """Whether this process is one of the node executables: ``ros2 run`` (the console
    script, named after the node), ``python -m brace_control.nodes.<node>``, or the
    bring-up's ``python -c 'from brace_control.nodes.<node> import main ...'``."""
    import sys
    if _os.path.splitext(_os.path.basename(sys.argv[0]))[0] in NODE_NAMES:
        return True
    argv = list(getattr(sys, 'orig_argv', ()))
    for flag, value in zip(argv, argv[1:]):
        if flag == '-m' and value in {f'{__name__}.{n}' for n in NODE_NAMES}:
            return True
        if flag == '-c' and any(f'from {__name__}.{n} import main' in value for n in NODE_NAMES):
            return True
    return False


#: a stop signal came while the node's process still imported (:func:`_stop_while_starting`):
#: ``runner.run_node`` stops at once when it is set, should the ``SystemExit`` have been lost
STOPPED_WHILE_STARTING = False


def _stop_while_starting() -> None:
    """A node process stopped by a signal while it still imports (rclpy and the message types
    take about a second) ends cleanly, exit code 0, as it does once it runs (``runner``):
    Ctrl-C right after ``ros2 run``, or a bring-up that stops its nodes as they start, would
    otherwise print a ``KeyboardInterrupt`` traceback (SIGINT) or end by the signal (the
    others). ``runner.run_node`` installs its own handlers before anything else."""
    import signal

    def leave(signum, frame):
        global STOPPED_WHILE_STARTING
        STOPPED_WHILE_STARTING = True   # kept: an import that swallows the SystemExit below
        raise SystemExit(0)             # (a broad except, a finaliser) must not lose the stop
    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP, signal.SIGQUIT):
        if signal.getsignal(sig) in (signal.SIG_DFL, signal.default_int_handler):
            signal.signal(sig, leave)


if _started_as_a_node():
    _stop_while_starting()
