"""package.xml declares what the code imports (a ROS install resolves it with rosdep).

The imports are read from the source (``ast``), not from a list kept by hand. Whether an
imported module is a ROS package is decided independently of package.xml: it is one when a
``ros-*`` distribution provides it here (the ROS 2 wheels of requirements.txt, e.g.
``ros-rclpy``, ``ros-geometry-msgs``), and every import of a launch file is one (launch
files run under ``ros2 launch``). Other third-party modules need their rosdep key, which by
the Debian naming rule is ``python3-<module>`` (``python3-yaml`` for ``yaml``), or must be
listed below as pip-only with the reason.
"""
from __future__ import annotations

import ast
import importlib.metadata
import re
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
PACKAGE = 'brace_control'

#: third-party modules with no rosdep key: pip installs them (requirements.txt, by this
#: distribution name); package.xml says so in a comment
PIP_ONLY = {'canopen': 'canopen', 'ruckig': 'ruckig', 'rosbags': 'rosbags'}
#: imported only conditionally (under ``try: ... except ImportError`` or an
#: ``if sys.version_info ...`` test): which one a Python uses, and where it comes from
CONDITIONAL = {
    'compression': 'compression.zstd: the standard library from Python 3.14',
    'backports': 'backports.zstd: a dependency of rosbags (pip), used before Python 3.14',
}


def _imports(path: Path) -> dict[str, bool]:
    """Top-level modules imported by ``path`` -> True when every import of it is conditional:
    in the body of a ``try`` that catches ``ImportError`` / ``ModuleNotFoundError``, or in a
    branch of an ``if`` on ``sys.version_info`` (relative imports are skipped)."""
    tree = ast.parse(path.read_text(), filename=str(path))
    guarded_nodes: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Try) and any(_catches_import_error(h) for h in node.handlers):
            guarded_nodes |= {id(n) for stmt in node.body for n in ast.walk(stmt)}
        elif isinstance(node, ast.If) and 'version_info' in ast.unparse(node.test):
            guarded_nodes |= {id(n) for stmt in node.body + node.orelse for n in ast.walk(stmt)}
    found: dict[str, bool] = {}
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names = [node.module]
        else:
            continue
        for name in names:
            top = name.split('.')[0]
            found[top] = found.get(top, True) and id(node) in guarded_nodes
    return found


def _catches_import_error(handler: ast.ExceptHandler) -> bool:
    kinds = handler.type.elts if isinstance(handler.type, ast.Tuple) else [handler.type]
    return any(isinstance(k, ast.Name) and k.id in ('ImportError', 'ModuleNotFoundError')
               for k in kinds)


def _code_imports() -> dict[str, dict[str, bool]]:
    """module -> {file: guarded} over brace_control/**/*.py, without stdlib and ourselves."""
    out: dict[str, dict[str, bool]] = {}
    for path in sorted((REPO / PACKAGE).rglob('*.py')):
        for module, guarded in _imports(path).items():
            if module in sys.stdlib_module_names or module in ('__future__', PACKAGE):
                continue
            out.setdefault(module, {})[str(path.relative_to(REPO))] = guarded
    return out


def _exec_depends() -> set[str]:
    root = ET.parse(REPO / 'package.xml').getroot()
    return {e.text.strip() for e in root.iter() if e.tag in ('exec_depend', 'depend') and e.text}


def _is_ros_package(module: str, dists: dict[str, list[str]]) -> bool:
    return any(d.lower().startswith('ros-') for d in dists.get(module, ()))


def test_the_ros_package_rule_recognises_rclpy_and_not_numpy():
    dists = importlib.metadata.packages_distributions()
    assert _is_ros_package('rclpy', dists) and _is_ros_package('geometry_msgs', dists)
    assert not _is_ros_package('numpy', dists) and not _is_ros_package('can', dists)


def test_every_ros_package_the_code_imports_is_an_exec_depend():
    dists = importlib.metadata.packages_distributions()
    ros = {m for m in _code_imports() if _is_ros_package(m, dists)}
    assert 'rclpy' in ros                              # the scan sees the nodes' imports
    missing = sorted(ros - _exec_depends())
    assert not missing, f'package.xml lacks <exec_depend> for {missing}'


def test_every_launch_file_import_is_an_exec_depend():
    launch_imports = set()
    for path in sorted((REPO / 'launch').glob('*.py')):
        launch_imports |= {m for m in _imports(path)
                           if m not in sys.stdlib_module_names and m != 'brace_control'}   # itself
    assert {'launch', 'launch_ros'} <= launch_imports
    missing = sorted(launch_imports - _exec_depends())
    assert not missing, f'package.xml lacks <exec_depend> for {missing} (imported by launch/)'


def test_every_other_python_dependency_has_its_rosdep_key_or_is_pip_only():
    dists = importlib.metadata.packages_distributions()
    depends = _exec_depends()
    problems = []
    for module, files in sorted(_code_imports().items()):
        if _is_ros_package(module, dists):
            continue
        if module in CONDITIONAL:
            unguarded = [f for f, guarded in files.items() if not guarded]
            if unguarded:
                problems.append(f'{module} ({CONDITIONAL[module]}) imported unconditionally in '
                                f'{unguarded}')
        elif module in PIP_ONLY:
            if f'python3-{module}' in depends:
                problems.append(f'{module} is listed pip-only here but package.xml has python3-{module}')
        elif f'python3-{module}' not in depends:
            problems.append(f'{module} (imported by {sorted(files)}) needs <exec_depend>'
                            f'python3-{module}</exec_depend> or an entry in PIP_ONLY')
    assert not problems, '\n'.join(problems)


def test_pip_only_dependencies_are_in_requirements_and_said_in_package_xml():
    pinned = {re.split(r'[=<>~!\[; ]', line, maxsplit=1)[0].lower()
              for line in (REPO / 'requirements.txt').read_text().splitlines()
              if line.strip() and not line.startswith('#')}
    xml_text = (REPO / 'package.xml').read_text()
    comment = ' '.join(re.findall(r'<!--(.*?)-->', xml_text, flags=re.S))
    for module, dist in PIP_ONLY.items():
        assert dist.lower() in pinned, f'{dist} (for {module}) is not in requirements.txt'
        assert module in comment, f'package.xml does not say that {module} comes from pip'
