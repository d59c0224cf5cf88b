"""Imports point one way: simulation <- learning <- deployment <- ROS plumbing <- nodes <- tools.

Each project module belongs to one layer (by its path, LAYERS below); a
module may import project modules of its own layer or of the layers listed
as below it, and some layers may not import certain third-party packages at
all. Checked by reading every source file's imports (AST, so an import inside
a function counts too), and, for the two controller nodes, by importing them
in a fresh interpreter and looking at what was loaded.
"""

import ast
from pathlib import Path
import subprocess
import sys

import pytest

REPO = Path(__file__).resolve().parents[1]

# layer -> (module prefixes in it, layers it may import, third-party roots it may not import)
LAYERS = {
    'simulation': (('sim_node.families', 'sim_node.env', 'sim_node.layout',
                    'sim_node.stepper', 'sim_node.swaps', 'sim_node.camera', 'sim_node.sawyer'),
                   (), ('rclpy', 'torch', 'zeus_msgs', 'zeus_ros')),
    'learning': (('zeus_ros.core',), (), ('rclpy', 'sim_node', 'mujoco', 'dm_control')),
    'deployment': (('zeus_ros.deploy',),
                   ('learning',), ('rclpy', 'sim_node', 'mujoco', 'dm_control')),
    'plumbing': (('zeus_ros.ros', 'sim_node.protocol'),
                 ('simulation_pure', 'learning', 'deployment'),
                 ('mujoco', 'dm_control', 'torch')),
    'nodes': (('sim_node.node', 'zeus_ros.context_node', 'zeus_ros.policy_node'),
              ('simulation', 'learning', 'deployment', 'plumbing'), ()),
}
# Simulation modules free of MuJoCo, which the plumbing may use.
SIMULATION_PURE = ('sim_node.families', 'sim_node.layout')
# Everything else under zeus_ros/ (train, evaluate, demo, bringup, sweeps...) is a tool.


def module_name(path: Path) -> str:
    rel = path.relative_to(REPO).with_suffix('')
    parts = list(rel.parts)
    if parts[-1] == '__init__':
        parts = parts[:-1]
    return '.'.join(parts)


def layer_of(module: str) -> str:
    for layer, (prefixes, _, _) in LAYERS.items():
        if any(module == p or module.startswith(p + '.') for p in prefixes):
            return layer
    return 'tools'


def imports_of(path: Path) -> set[str]:
    tree = ast.parse(path.read_text())
    found = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            found.add(node.module)
    return found


def sources():
    for package in ('sim_node', 'zeus_ros'):
        yield from sorted((REPO / package).rglob('*.py'))


def violations() -> list[str]:
    found = []
    for path in sources():
        module = module_name(path)
        layer = layer_of(module)
        if layer == 'tools':
            continue
        _, allowed, forbidden = LAYERS[layer]
        for imported in imports_of(path):
            root = imported.split('.')[0]
            if root in forbidden:
                if not _pure_simulation_allowed(layer, imported):
                    found.append(f'{module} ({layer}) imports {imported}')
                continue
            if root in ('sim_node', 'zeus_ros'):
                target = layer_of(imported)
                if layer == target == 'nodes':
                    found.append(f'{module} (a node) imports another node, {imported}')
                    continue
                if target == layer or target in allowed or _pure_simulation_allowed(
                        layer, imported):
                    continue
                found.append(f'{module} ({layer}) imports {imported} ({target})')
    return found


def _pure_simulation_allowed(layer: str, imported: str) -> bool:
    _, allowed, _ = LAYERS[layer]
    return 'simulation_pure' in allowed and any(
        imported == p or imported.startswith(p + '.') for p in SIMULATION_PURE)


def test_imports_point_one_way():
    assert violations() == []


def test_the_rule_catches_a_reverse_import(tmp_path, monkeypatch):
    """A learning-core module importing the simulation or a node is reported."""
    bad = REPO / 'zeus_ros' / 'core' / '_layer_probe.py'
    bad.write_text('from sim_node.env import ParamEnv\nimport zeus_ros.context_node\n')
    try:
        found = violations()
    finally:
        bad.unlink()
    assert any('_layer_probe' in v and 'sim_node.env' in v for v in found), found
    assert any('_layer_probe' in v and 'context_node' in v for v in found), found


@pytest.mark.parametrize('node', ['zeus_ros.context_node', 'zeus_ros.policy_node'])
def test_controller_nodes_never_load_mujoco(node):
    code = (f'import sys, {node}\n'
            "print(sorted(m for m in ('mujoco', 'dm_control', 'sim_node.env') "
            'if m in sys.modules))')
    out = subprocess.run([sys.executable, '-c', code], cwd=REPO, capture_output=True,
                         text=True, check=True).stdout.strip()
    assert out == '[]', f'{node} loads {out}'
