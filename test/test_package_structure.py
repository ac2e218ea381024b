"""The package's own structure, read from its source with ``ast`` (not by importing it):
no import cycle between its modules, no ``except ImportError`` around its own modules, and
one list of the nodes that every copy follows."""
from __future__ import annotations

import ast
import os
import re
from pathlib import Path

from brace_control.nodes import NODE_NAMES

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / 'brace_control'


def modules() -> dict[str, tuple[Path, bool]]:
    """Dotted module name -> (file, is a package's ``__init__``)."""
    out = {}
    for path in PACKAGE.rglob('*.py'):
        parts = list(path.relative_to(ROOT).with_suffix('').parts)
        is_pkg = parts[-1] == '__init__'
        out['.'.join(parts[:-1] if is_pkg else parts)] = (path, is_pkg)
    return out


def _targets(module: str, is_pkg: bool, node: ast.Import | ast.ImportFrom) -> list[str]:
    if isinstance(node, ast.Import):
        return [a.name for a in node.names]
    if node.level:
        base = module.split('.') if is_pkg else module.split('.')[:-1]
        base = base[:len(base) - (node.level - 1)]
        target = '.'.join(base + ([node.module] if node.module else []))
    else:
        target = node.module or ''
    return [target] + [f'{target}.{a.name}' for a in node.names]


def _type_checking_only(tree: ast.AST) -> set[int]:
    skip = set()
    for n in ast.walk(tree):
        if isinstance(n, ast.If) and 'TYPE_CHECKING' in ast.unparse(n.test):
            skip.update(id(m) for m in ast.walk(n))
    return skip


def import_graph() -> dict[str, set[str]]:
    """Every import of a package module by another, at module level or inside a function
    (a deferred import is still a dependency), except those only for type checkers and a
    module's imports of its own parent packages."""
    mods = modules()
    graph: dict[str, set[str]] = {m: set() for m in mods}
    for mod, (path, is_pkg) in mods.items():
        tree = ast.parse(path.read_text(encoding='utf-8'))
        skip = _type_checking_only(tree)
        for n in ast.walk(tree):
            if isinstance(n, (ast.Import, ast.ImportFrom)) and id(n) not in skip:
                for t in _targets(mod, is_pkg, n):
                    if t in mods and t != mod and not mod.startswith(t + '.'):
                        graph[mod].add(t)
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                found.append(sorted(comp))

    for v in graph:
        if v not in index:
            visit(v)
    return found


def test_the_cycle_finder_finds_a_cycle():
    assert cycles({'a': {'b'}, 'b': {'c'}, 'c': {'a'}, 'd': {'a'}}) == [['a', 'b', 'c']]
    assert cycles({'a': {'b'}, 'b': set()}) == []


def test_no_import_cycle_between_the_package_s_modules():
    graph = import_graph()
    assert 'brace_control.demo_session' in graph['brace_control.demo_interaction']
    assert not cycles(graph), cycles(graph)


def test_no_except_import_error_around_the_package_s_own_modules():
    """A guard around our own import turns a broken module into a check that silently does
    nothing (a ``None`` mechanism: no wrench limit)."""
    guarded = []
    for mod, (path, is_pkg) in modules().items():
        for n in ast.walk(ast.parse(path.read_text(encoding='utf-8'))):
            if not isinstance(n, ast.Try):
                continue
            catches = {ast.unparse(h.type) for h in n.handlers if h.type is not None}
            if not any('ImportError' in c or 'ModuleNotFoundError' in c for c in catches):
                continue
            for inner in n.body:
                for m in ast.walk(inner):
                    if isinstance(m, (ast.Import, ast.ImportFrom)) and any(
                            t.startswith('brace_control') for t in _targets(mod, is_pkg, m)):
                        guarded.append(f'{path.relative_to(ROOT)}:{m.lineno}')
    assert not guarded, guarded


def test_one_node_list_followed_by_setup_launch_and_readme():
    setup = (ROOT / 'setup.py').read_text(encoding='utf-8')
    scripts = dict(re.findall(r"'(\w+) = (brace_control\.nodes\.\w+):main'", setup))
    assert set(scripts) == set(NODE_NAMES)
    assert all(scripts[n] == f'brace_control.nodes.{n}' for n in NODE_NAMES)
    assert all((PACKAGE / 'nodes' / f'{n}.py').is_file() for n in NODE_NAMES)
    launch = (ROOT / 'launch' / 'brace.launch.py').read_text(encoding='utf-8')
    assert 'from brace_control.nodes import' in launch and 'NODE_NAMES' in launch
    readme = (ROOT / 'README.md').read_text(encoding='utf-8')
    assert all(f'`{n}`' in readme for n in NODE_NAMES)
    words = {3: 'three', 4: 'four', 5: 'five', 6: 'six'}
    counted = re.findall(r'\b(three|four|five|six) nodes\b', readme)
    assert counted and set(counted) == {words[len(NODE_NAMES)]}, counted


#: the four nodes other than the driver, imported
NODE_IMPORTS = ('import brace_control.nodes.kinetics_node, brace_control.nodes.trajectory_node, '
                'brace_control.nodes.ik_node, brace_control.nodes.interaction_node')


def _python_lines(code: str) -> list[str]:
    """What a fresh interpreter running ``code`` prints, line by line (it must succeed)."""
    import subprocess
    import sys
    out = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True, timeout=60,
                         check=False)
    assert out.returncode == 0, out.stderr[-2000:]
    return out.stdout.strip().splitlines()


def test_a_node_that_needs_only_the_units_does_not_load_the_master():
    """``brace_control.can`` loads its names on first use (PEP 562): kinetics_node and
    trajectory_node import ``can.units``, and every node's configuration check reads
    ``can.state``; none of them loads the master (with canopen's network and the cycle),
    0.3-0.4 s of CPU at each start before. The package's names still all resolve."""
    code = ('import sys\n'
            f'{NODE_IMPORTS}\n'
            'from brace_control.can.units import scaling_from_config\n'
            'print(sorted(m for m in sys.modules if m.startswith("brace_control.can.")))\n'
            'import brace_control.can as can\n'
            'assert all(getattr(can, n) is not None for n in can.__all__)\n'
            'assert can.CiA402Master is can.BraceMaster\n')
    loaded = _python_lines(code)[0]
    assert 'brace_control.can.units' in loaded
    for heavy in ('brace_control.can.master', 'brace_control.can.cycle', 'brace_control.can.boot'):
        assert f"'{heavy}'" not in loaded, loaded


def test_a_node_checking_a_device_file_loads_neither_canopen_nor_python_can():
    """Every node checks the whole device file at its start, its CAN set-up included
    (``MasterConfig.from_device_config``). That reads no dictionary and opens no bus, so the
    nodes other than the driver do not pay canopen's and python-can's import (about 65 ms of
    CPU each, four of them per stack). The driver's path still has them: reading a
    dictionary loads canopen, and a dictionary error is python-can's kind of error."""
    code = ('import sys\n'
            f'{NODE_IMPORTS}\n'
            'from brace_control.checks import check_device\n'
            'from brace_control.config import load_device_config\n'
            'for name in ("lumbar_brace", "shoulder", "neck_brace_4rpr", "upper_limb_trainer"):\n'
            '    check_device(load_device_config(name))\n'
            'print(sorted(m for m in ("can", "canopen") if m in sys.modules))\n'
            'from brace_control.can.dictionary import Dictionary\n'
            'from brace_control.config import config_dir\n'
            'Dictionary(config_dir() / "lumbar_drive.eds", node_id=1)\n'
            'from brace_control.can.plan import DictionaryError\n'
            'print(sorted(m for m in ("can", "canopen") if m in sys.modules), DictionaryError.__mro__[1].__name__)\n')
    checked, read = _python_lines(code)[-2:]
    assert checked == '[]', checked
    assert read == "['can', 'canopen'] DriverInitializationError", read


def test_the_dictionarys_data_type_codes_are_canopens():
    """The CiA 301 data type indices :mod:`brace_control.can.dictionary` names itself (so
    that it need not import canopen) are those canopen reads from an EDS."""
    from canopen import objectdictionary as od

    from brace_control.can import dictionary, errors, plan
    names = ('BOOLEAN', 'INTEGER8', 'INTEGER16', 'INTEGER24', 'INTEGER32', 'INTEGER64', 'UNSIGNED8',
             'UNSIGNED16', 'UNSIGNED24', 'UNSIGNED32', 'UNSIGNED64', 'REAL32', 'REAL64',
             'VISIBLE_STRING', 'DOMAIN')
    assert {n: getattr(dictionary, n) for n in names} == {n: getattr(od, n) for n in names}
    assert {dictionary.type_name(getattr(od, n)) for n in names} == set(names)
    assert plan.DictionaryError is errors.DictionaryError
    import can
    assert issubclass(plan.DictionaryError, can.CanInitializationError)


def test_the_fast_dds_2_profile_is_the_same_profile_in_its_own_spelling():
    """config/fastdds2_discovery.xml (Humble, Jazzy) holds the same elements and values as
    config/fastdds_discovery.xml (Kilted), the writer's times spelled as Fast DDS 2's XML
    spells them (camel case), and the writers' heartbeat is the 0.1 s both promise."""
    import re
    import xml.etree.ElementTree as ET

    from brace_control.config import config_dir

    def flat(path, camel):
        out = []
        for el in ET.parse(path).iter():
            tag = el.tag
            if camel:       # heartbeatPeriod -> heartbeat_period
                tag = re.sub(r'(?<=[a-z])([A-Z])', lambda m: '_' + m.group(1).lower(), tag)
            out.append((tag, (el.text or '').strip(), tuple(sorted(el.attrib.items()))))
        return out
    three = flat(config_dir() / 'fastdds_discovery.xml', camel=False)
    two = flat(config_dir() / 'fastdds2_discovery.xml', camel=True)
    # the discovery part's own names are camel case in both: compare after the same mapping
    three_cmp = [(re.sub(r'(?<=[a-z])([A-Z])', lambda m: '_' + m.group(1).lower(), t), x, a)
                 for t, x, a in three]
    assert two == three_cmp
    raw_two = ET.parse(config_dir() / 'fastdds2_discovery.xml')
    raw_three = ET.parse(config_dir() / 'fastdds_discovery.xml')
    for tree, tag in ((raw_two, 'heartbeatPeriod'), (raw_three, 'heartbeat_period')):
        (period,) = tree.iter(tag)
        assert (period.findtext('sec'), period.findtext('nanosec')) == ('0', '100000000')
        writer = next(tree.iter('data_writer'))
        assert writer.get('is_default_profile') == 'true'


def test_the_discovery_profile_is_taken_unless_the_user_has_one():
    """``use_discovery_profile`` points Fast DDS 3's variable at the package's profile, and
    Fast DDS 2's too on Humble, Iron and Jazzy (Kilted's RMW warns at every participant when
    that one is set); it leaves a user's own profile and another RMW alone; and the Fast DDS
    this package runs on reads the file without an XML error or a warning."""
    import subprocess
    import sys

    from brace_control.config import config_dir
    from brace_control.nodes.dds import PROFILE_VARIABLES, use_discovery_profile
    ours = str(config_dir() / 'fastdds_discovery.xml')
    env: dict[str, str] = {}
    assert use_discovery_profile(env) == ours
    assert env == {'FASTDDS_DEFAULT_PROFILES_FILE': ours}
    ours_2 = str(config_dir() / 'fastdds2_discovery.xml')           # Fast DDS 2's XML
    for distro in ('humble', 'jazzy'):
        env = {'ROS_DISTRO': distro}
        assert use_discovery_profile(env) == ours_2
        assert env == {'ROS_DISTRO': distro, **dict.fromkeys(PROFILE_VARIABLES, ours_2)}
    env = {'RMW_IMPLEMENTATION': 'rmw_fastrtps_dynamic_cpp'}
    assert use_discovery_profile(env) == ours and env['FASTDDS_DEFAULT_PROFILES_FILE'] == ours
    for name in PROFILE_VARIABLES:
        env = {name: '/home/lab/my_profile.xml'}
        assert use_discovery_profile(env) is None and env == {name: '/home/lab/my_profile.xml'}
    env = {'RMW_IMPLEMENTATION': 'rmw_cyclonedds_cpp'}
    assert use_discovery_profile(env) is None and list(env) == ['RMW_IMPLEMENTATION']
    code = ('import rclpy\nrclpy.init()\nnode = rclpy.create_node("profile_probe")\n'
            'node.destroy_node()\nrclpy.shutdown()\nprint("participant made")\n')
    run_env = {k: v for k, v in os.environ.items() if k not in PROFILE_VARIABLES}
    use_discovery_profile(run_env)
    out = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True, timeout=60,
                         env=run_env, check=False)
    assert out.returncode == 0 and 'participant made' in out.stdout, out.stderr[-2000:]
    assert 'XMLPARSER' not in out.stderr and 'Error' not in out.stderr, out.stderr[-2000:]
    assert 'WARN' not in out.stderr, out.stderr[-2000:]
