"""Imports point one way: simulation <- learning <- deployment <- ROS plumbing <- nodes <- tools.

Every product module (each .py file under sim_node/ and zeus_ros/) belongs to
one layer, by its path (LAYERS below); a file in no layer fails the test. A
module may import project modules of its own layer or of the layers listed as
below it, and some layers may not import certain third-party packages at all
(the simulation neither ROS nor torch; the learning core torch but no ROS;
deployment no ROS). Checked by reading every source file's imports (AST, so an
import inside a function counts too; relative imports resolved; the literal
names given to importlib.import_module / __import__ counted), and, for the
two controller nodes, by importing them in a fresh interpreter and looking at
what was loaded.
"""

import ast
from pathlib import Path
import shutil
import subprocess
import sys

import pytest

REPO = Path(__file__).resolve().parents[1]

# The ROS client library and the ROS packages the product imports (messages,
# services, ament): none of them in the simulation, the learning core,
# deployment or the offline learning tools.
ROS = ('rclpy', 'zeus_msgs', 'sensor_msgs', 'std_msgs', 'std_srvs', 'builtin_interfaces',
       'rcl_interfaces', 'diagnostic_msgs', 'rosgraph_msgs', 'rosidl_runtime_py',
       'ament_index_python', 'launch', 'launch_ros', 'rosbag2_py', 'foxglove_msgs')
MUJOCO = ('mujoco', 'dm_control')

# layer -> (module prefixes in it, layers it may import, third-party roots it may not import)
LAYERS = {
    'simulation': (('sim_node',), (), ROS + ('torch', 'zeus_ros')),
    'learning': (('zeus_ros.core',), (), ROS + MUJOCO + ('sim_node',)),
    # The deployed metadata is checked against the families' MuJoCo-free tables.
    'deployment': (('zeus_ros.deploy',), ('learning', 'simulation_pure'), ROS + MUJOCO),
    'plumbing': (('zeus_ros.ros',), ('simulation_pure', 'learning', 'deployment'),
                 MUJOCO + ('torch',)),
    'nodes': (('zeus_ros.nodes',), ('simulation', 'learning', 'deployment', 'plumbing'), ()),
    # Offline programs: train, evaluate, reports, sweeps, export. They never start ROS.
    'learning_tools': (('zeus_ros.learning_tools',),
                       ('simulation', 'learning', 'deployment'), ROS),
    # Programs that start, drive or watch the graph; they may run an offline tool's code.
    'ros_tools': (('zeus_ros.ros_tools',), ('simulation', 'learning', 'deployment', 'plumbing',
                                            'nodes', 'learning_tools'), ()),
}
# The package itself (zeus_ros/__init__.py): imported before any of its layers, so it
# imports nothing of the project and nothing heavy.
PACKAGE_ROOT = 'zeus_ros'
# Simulation modules free of MuJoCo, which deployment and the plumbing may use.
SIMULATION_PURE = ('sim_node.families', 'sim_node.family_file', 'sim_node.layout',
                   'sim_node.structures')
# The one plumbing module that reaches MuJoCo: the sim node's camera publisher draws
# with the simulation's renderer. Only the sim node imports it (the controller
# nodes' processes never load MuJoCo: test_controller_nodes_never_load_mujoco).
PLUMBING_THAT_RENDERS = {'zeus_ros.ros.camera': ('sim_node.camera',)}


def module_name(path: Path, root: Path = REPO) -> str:
    rel = path.relative_to(root).with_suffix('')
    parts = list(rel.parts)
    if parts[-1] == '__init__':
        parts = parts[:-1]
    return '.'.join(parts)


def _within(module: str, prefixes) -> bool:
    return any(module == p or module.startswith(p + '.') for p in prefixes)


def layer_of(module: str) -> str | None:
    """Return the layer of a project module; None for a module in no layer."""
    if module == PACKAGE_ROOT:
        return 'root'
    for layer, (prefixes, _, _) in LAYERS.items():
        if _within(module, prefixes):
            return layer
    return None


def _resolve(module: str, is_package: bool, level: int, name: str | None) -> str:
    """Return the absolute name of `from <dots><name> import ...` written in `module`."""
    parts = module.split('.')
    base = parts if is_package else parts[:-1]
    base = base[:len(base) - (level - 1)]
    return '.'.join(base + ([name] if name else []))


def _literal_import(node: ast.Call) -> str | None:
    """Return the module named by a call like importlib.import_module('x')."""
    func = node.func
    called = func.attr if isinstance(func, ast.Attribute) else getattr(func, 'id', None)
    if called not in ('import_module', '__import__') or not node.args:
        return None
    first = node.args[0]
    return first.value if isinstance(first, ast.Constant) and isinstance(first.value, str) \
        else None


def imports_of(text: str, module: str = '', is_package: bool = False) -> set[str]:
    """Return every module a source text imports: absolute, relative (resolved), by literal."""
    found = set()
    for node in ast.walk(ast.parse(text)):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module if node.level == 0 else _resolve(
                module, is_package, node.level, node.module)
            found.add(base)
            # `from package import module` imports that module (a name that is a
            # class falls in its module's layer anyway).
            found.update(f'{base}.{alias.name}' for alias in node.names if alias.name != '*')
        elif isinstance(node, ast.Call) and (named := _literal_import(node)):
            found.add(named)
    return {name for name in found if name}


def sources(root: Path = REPO):
    for package in ('sim_node', 'zeus_ros'):
        yield from sorted((root / package).rglob('*.py'))


def check_module(module: str, text: str, is_package: bool = False) -> list[str]:
    """Return what is wrong with the imports of one module (its name and source text)."""
    layer = layer_of(module)
    if layer is None:
        return [f'{module} is in no layer: add its folder to LAYERS in test/test_layers.py']
    if layer == 'root':
        allowed, forbidden = (), ROS + MUJOCO + ('torch', 'sim_node')
    else:
        _, allowed, forbidden = LAYERS[layer]
    found = []
    for imported in sorted(imports_of(text, module, is_package)):
        problem = _import_problem(module, layer, allowed, forbidden, imported)
        if problem:
            found.append(f'{module} ({layer}) {problem}')
    return found


def _import_problem(module, layer, allowed, forbidden, imported) -> str | None:
    root = imported.split('.')[0]
    if _within(imported, PLUMBING_THAT_RENDERS.get(module, ())):
        return None
    if 'simulation_pure' in allowed and _within(imported, SIMULATION_PURE):
        return None
    if root in forbidden:
        return f'imports {imported}'
    if root not in ('sim_node', PACKAGE_ROOT) or imported == PACKAGE_ROOT:
        return None
    target = layer_of(imported)
    if layer == target == 'nodes' and imported != 'zeus_ros.nodes':
        return f'(a node) imports another node, {imported}'
    if target == layer or target in allowed:
        return None
    return f'imports {imported} ({target})'


def violations(root: Path = REPO) -> list[str]:
    found = []
    for path in sources(root):
        found += check_module(module_name(path, root), path.read_text(),
                              path.name == '__init__.py')
    return found


def test_imports_point_one_way():
    assert violations() == []


def with_probe(tmp_path, relative: str, text: str, check):
    """Return `check(root)` on a copy of the product's sources with a probe module added.

    A copy, not the checkout: a probe written into the checkout is seen, while
    it exists, by every test that reads the sources (the import rules, ruff),
    and under pytest-xdist those run at the same moment in other workers.
    """
    root = tmp_path / 'checkout'
    for folder in PRODUCT:
        shutil.copytree(REPO / folder, root / folder,
                        ignore=shutil.ignore_patterns('__pycache__'))
    (root / relative).write_text(text)
    return check(root)


def test_the_rule_catches_a_reverse_import(tmp_path):
    """A learning-core module importing the simulation or a node is reported."""
    found = with_probe(tmp_path, 'zeus_ros/core/_layer_probe.py',
                       'from sim_node.env import ParamEnv\nimport zeus_ros.nodes.context_node\n',
                       violations)
    assert any('_layer_probe' in v and 'sim_node.env' in v for v in found), found
    assert any('_layer_probe' in v and 'context_node' in v for v in found), found


def test_a_file_in_no_layer_fails():
    """A new top-level module (or folder) must be given a layer, not pass unchecked."""
    assert check_module('zeus_ros.train', 'import numpy\n') == [
        'zeus_ros.train is in no layer: add its folder to LAYERS in test/test_layers.py']
    assert check_module('sim_node.node', '') == []     # the whole simulation is one layer
    assert check_module('zeus_ros.newthing.tool', '')[0].endswith('is in no layer: add its '
                                                                  'folder to LAYERS in '
                                                                  'test/test_layers.py')


@pytest.mark.parametrize('module, text, reported', [
    # ROS and torch where they do not belong
    ('sim_node.env', 'import rclpy\n', 'imports rclpy'),
    ('sim_node.env', 'def f():\n    from sensor_msgs.msg import Image\n', 'sensor_msgs'),
    ('sim_node.stepper', 'import torch\n', 'imports torch'),
    ('zeus_ros.core.agent', 'from rclpy.node import Node\n', 'imports rclpy'),
    ('zeus_ros.deploy.inference', 'import rclpy\n', 'imports rclpy'),
    ('zeus_ros.ros.util', 'import torch\n', 'imports torch'),
    ('zeus_ros.learning_tools.train', 'import rclpy\n', 'imports rclpy'),
    # upward imports, also relative and through importlib
    ('zeus_ros.core.agent', 'from ..nodes import policy_node\n', 'zeus_ros.nodes.policy_node'),
    ('zeus_ros.deploy.checkpoint', 'from ..ros.util import stamp_ns\n', 'zeus_ros.ros.util'),
    ('zeus_ros.core.agent', 'from .. import learning_tools\n', 'zeus_ros.learning_tools'),
    ('zeus_ros.core.config', "import importlib\nimportlib.import_module('zeus_ros.deploy')\n",
     'zeus_ros.deploy (deployment)'),
    ('sim_node.env', "__import__('rclpy')\n", 'imports rclpy'),
    ('zeus_ros.learning_tools.sweep', 'from zeus_ros.ros_tools import demo\n', 'ros_tools'),
    ('zeus_ros.ros.camera', 'from sim_node.env import ParamEnv\n', 'sim_node.env'),
    ('zeus_ros.nodes.sim_node', 'from .context_node import ContextNode\n', 'another node'),
])
def test_each_rule_reports_a_breach(module, text, reported):
    found = check_module(module, text)
    assert any(reported in v for v in found), found


def test_a_relative_import_in_a_package_resolves_from_the_package():
    # zeus_ros/core/__init__.py: `from ..ros import util` is zeus_ros.ros.util
    assert imports_of('from ..ros import util\n', 'zeus_ros.core', is_package=True) == {
        'zeus_ros.ros', 'zeus_ros.ros.util'}
    assert check_module('zeus_ros.core', 'from .. import nodes\n', is_package=True) != []


@pytest.mark.parametrize('module, text', [
    ('zeus_ros.core.agent', 'import torch\n'),                       # the core may use torch
    ('zeus_ros.deploy.metadata', 'from sim_node.families import get_family\n'),
    ('zeus_ros.ros.camera', 'from sim_node.camera import SimCamera\n'),
    ('zeus_ros.ros_tools.check_parity', 'from zeus_ros.learning_tools.evaluate import x\n'),
    ('sim_node.sawyer', 'from .layout import StepResult\n'),
])
def test_what_the_rules_allow_passes(module, text):
    assert check_module(module, text) == []


def import_graph() -> dict[str, set[str]]:
    """Return module -> the product modules it imports (at the top or inside a function)."""
    texts = {module_name(path): (path.read_text(), path.name == '__init__.py')
             for path in sources()}
    graph = {}
    for module, (text, is_package) in texts.items():
        graph[module] = set()
        for name in imports_of(text, module, is_package):
            while name and name not in texts:   # `from a.b import Class` is module a.b
                name = name.rpartition('.')[0]
            if name and name != module:
                graph[module].add(name)
    return graph


def circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Return one import circle through each module that is on one (depth-first search)."""
    found, done = [], set()

    def visit(module, path):
        if module in path:
            found.append(path[path.index(module):] + [module])
            return
        if module in done:
            return
        for imported in sorted(graph.get(module, ())):
            visit(imported, path + [module])
        done.add(module)

    for module in sorted(graph):
        visit(module, [])
    return found


def test_no_import_circles():
    assert circles(import_graph()) == []


def test_the_circle_check_finds_one():
    assert circles({'a': {'b'}, 'b': {'c'}, 'c': {'a'}, 'd': {'a'}}) == [['a', 'b', 'c', 'a']]
    assert circles({'a': {'b'}, 'b': set()}) == []


@pytest.mark.parametrize('node', ['zeus_ros.nodes.context_node', 'zeus_ros.nodes.policy_node'])
def test_controller_nodes_never_load_mujoco(node):
    code = (f'import sys, {node}\n'
            "print(sorted(m for m in ('mujoco', 'dm_control', 'sim_node.env') "
            'if m in sys.modules))')
    out = subprocess.run([sys.executable, '-c', code], cwd=REPO, capture_output=True,
                         text=True, check=True).stdout.strip()
    assert out == '[]', f'{node} loads {out}'


# research/ (reproductions, pilots, benchmarks, the soak) sits above every layer: its
# scripts import the product; nothing of the product imports, runs or packages research.
RESEARCH = REPO / 'research'
PRODUCT = ('sim_node', 'zeus_ros', 'scripts', 'launch')


def _code_strings(tree: ast.AST) -> list[str]:
    """Return the string constants of a module, its docstrings left out."""
    docstrings = {id(node.value) for node in ast.walk(tree)
                  if isinstance(node, ast.Expr) and isinstance(node.value, ast.Constant)}
    return [node.value for node in ast.walk(tree) if isinstance(node, ast.Constant)
            and isinstance(node.value, str) and id(node) not in docstrings]


def research_uses(root: Path = REPO) -> list[str]:
    """Return where product files import a research script or name research/ in code."""
    scripts = {'research'} | {path.stem for path in RESEARCH.rglob('*.py')}
    found = []
    for path in (p for folder in PRODUCT for p in sorted((root / folder).rglob('*.py'))):
        rel = path.relative_to(root)
        found += [f'{rel} imports {name}' for name in sorted(imports_of(path.read_text()))
                  if name.split('.')[0] in scripts]
        found += [f'{rel} names {text!r}' for text in _code_strings(ast.parse(path.read_text()))
                  if 'research' in Path(text).parts]
    return found


def test_the_product_never_uses_research():
    assert research_uses() == []


def test_research_is_not_packaged():
    """No __init__.py, so find_packages never picks it; setup.py's data files skip it."""
    assert list(RESEARCH.rglob('__init__.py')) == []
    assert 'research' not in (REPO / 'setup.py').read_text()


def test_the_research_rule_catches_an_import_and_a_path(tmp_path):
    found = with_probe(tmp_path, 'zeus_ros/_research_probe.py',
                       "import sys\nsys.path.insert(0, 'research/analysis')\n"
                       'from summarize_runs import mean_se\n', research_uses)
    assert any('_research_probe' in v and 'summarize_runs' in v for v in found), found
    assert any('_research_probe' in v and 'research/analysis' in v for v in found), found


def test_no_research_is_left_at_the_top_level():
    """The former top-level folders stay empty (a merge can leave a new run folder there)."""
    left = [path for name in ('repro', 'bench') for path in (REPO / name).rglob('*')
            if path.is_file() and '__pycache__' not in path.parts]
    assert left == [], 'move these under research/'
