"""metadata.json fuzz (#39): every leaf of shipped checkpoints' metadata, broken each way.

Each leaf (a JSON value that is not an object; a list is one leaf) is removed,
given the wrong type, made absurd, and (numbers, flags) moved a little. Loading
the result must either refuse it with one line that names the field (a
ValueError: MetadataRefused), or give a model that builds what the controller
nodes build at start and computes finite outputs. In process over every leaf;
then real controller processes started on bad files exit with that one line.
"""

from dataclasses import asdict
import json
import math
from pathlib import Path
import subprocess
import time

from conftest import REPO
import numpy as np
import pytest
import torch

from sim_node.env import make_env
from sim_node.families import get_sim_family, SIM_FAMILIES
from sim_node.structures import DOMAIN_STRUCTURES
from sim_driver import FAMILY, start_node
from zeus_ros.nodes.context_node import ContextGuard
from zeus_ros.core.config import config_types, settings_classes, ZeusConfig
from zeus_ros.core.window import ContextWindow
from zeus_ros.deploy.checkpoint import METADATA_FILE, MetadataRefused, MODEL_FILE
from zeus_ros.deploy.inference import InferenceModel
from zeus_ros.deploy.metadata import CONFIG_LIMITS, LATER_CONFIG_KEYS

# The oldest format (config keys added since absent), every config key with a
# learned encoder (up-osi; keys newer than it filled in with their defaults), and
# a family of two parameters with dropped velocities.
SHIPPED = ('walker-walk-v0-zeus', 'cheetah-run-v1-up-osi', 'sawyer-peg-v0-zeus')
REMOVED = object()


def original(name: str) -> dict:
    meta = json.loads((REPO / 'weights' / name / METADATA_FILE).read_text())
    if name == 'cheetah-run-v1-up-osi':
        # As the trainer wrote it while one config held every method's settings: every
        # config key, those added since with defaults (so the fuzz breaks each of them).
        every = {k: v for cls in settings_classes() for k, v in asdict(cls()).items()}
        meta['config'] = {**ZeusConfig().to_dict(), **every, **meta['config']}
    return meta


def leaves(node, path=()):
    """Paths of every non-object value (an empty object counts as a value)."""
    if isinstance(node, dict) and node:
        for key, value in node.items():
            yield from leaves(value, (*path, key))
    else:
        yield path


def absurd(value):
    """Return a value of the same type that no checkpoint could hold."""
    if isinstance(value, bool):
        return 'maybe'
    if isinstance(value, int):
        return 10 ** 12
    if isinstance(value, float):
        return 1e308
    if isinstance(value, str):
        return 'no-such-' + 'x' * 200
    if isinstance(value, list):
        return [absurd(v) for v in value]
    return -10 ** 12


def variants(value) -> list[tuple[str, object]]:
    """(label, new value) pairs for one leaf; REMOVED deletes it."""
    out = [('removed', REMOVED), ('absurd', absurd(value))]
    if isinstance(value, bool):
        out += [('wrong type', 'yes'), ('flipped', not value)]
    elif isinstance(value, int | float):
        out += [('wrong type', 'x'), ('negative', -absurd(value)), ('plus one', value + 1),
                ('minus one', value - 1)]
        if isinstance(value, float):
            out += [('NaN', math.nan), ('doubled', value * 2)]
    elif isinstance(value, str):
        out += [('wrong type', 12345), ('empty', '')]
    elif isinstance(value, list):
        out += [('wrong type', 'x'), ('empty', []), ('shorter', value[:-1])]
        if value:
            out += [('first mistyped', [{}] + value[1:]),
                    ('first absurd', [absurd(value[0])] + value[1:])]
    else:   # null or an empty object
        out += [('wrong type', 'x')]
    return out


def mutated(meta: dict, path: tuple, new) -> dict:
    meta = json.loads(json.dumps(meta))
    node = meta
    for key in path[:-1]:
        node = node[key]
    if new is REMOVED:
        del node[path[-1]]
    else:
        node[path[-1]] = new
    return meta


def weights_dir(tmp_path: Path, name: str, meta: dict) -> Path:
    """Make a checkpoint directory: the shipped tensors, `meta` as its metadata.json."""
    out = tmp_path / name
    out.mkdir(parents=True, exist_ok=True)
    if not (out / MODEL_FILE).exists():
        (out / MODEL_FILE).symlink_to(REPO / 'weights' / name / MODEL_FILE)
    (out / METADATA_FILE).write_text(json.dumps(meta))
    return out


def assert_acts_finitely(model: InferenceModel) -> None:
    """Build what the two controller nodes build at start; every output finite."""
    layout = model.meta.obs_layout.layout()
    assert layout.size == model.obs_dim
    assert len(model.meta.action_layout.actuator_names) == model.action_dim
    window = ContextWindow(model.k, model.obs_dim, model.action_dim)
    guard = ContextGuard(model)
    rng = np.random.default_rng(0)
    true = model.param_offset + model.param_scale if model.needs_true_param else None
    for rows, mask in (window.arrays(),
                       (rng.normal(size=(model.k, model.row_dim)), np.ones(model.k, bool))):
        latent, estimates, problem = guard.context(rows, mask, true)
        assert problem == '' and np.all(np.isfinite(latent))
        action = model.act(layout.observation(rng.normal(size=len(layout.joint_names)),
                                              rng.normal(size=len(layout.joint_names))),
                           latent)
        assert action.shape == (model.action_dim,) and np.all(np.abs(action) <= 1)
        with torch.no_grad():
            has_decoder = model.method.decode(torch.zeros(1, model.context_dim)) is not None
        # NaN is what Context.param_estimates means by 'no decoder'.
        assert np.all(np.isfinite(estimates)) if has_decoder else np.all(np.isnan(estimates))


def outcome(directory: Path, field: str) -> str | None:
    """Return what is wrong with loading `directory` whose `field` was broken, or None."""
    try:
        model = InferenceModel.load(directory)
    except MetadataRefused as error:
        message = str(error)
        if '\n' in message or field not in message:
            return f'refused without naming {field} on one line: {message}'
        return None
    try:
        assert_acts_finitely(model)
    except Exception as error:   # noqa: BLE001 - any failure of the loaded model is the finding
        return f'loaded, then {type(error).__name__}: {error}'
    return None


@pytest.mark.parametrize('name', SHIPPED)
def test_the_shipped_metadata_loads_and_acts(name, tmp_path):
    """The baseline: without it, a fuzz that refuses everything would pass."""
    assert outcome(weights_dir(tmp_path, name, original(name)), '') is None
    assert_acts_finitely(InferenceModel.load(REPO / 'weights' / name))


@pytest.mark.parametrize('name, path', [(name, path) for name in SHIPPED
                                        for path in leaves(original(name))],
                         ids=lambda v: '.'.join(v) if isinstance(v, tuple) else v)
def test_every_broken_leaf_is_refused_by_name_or_harmless(name, path, tmp_path):
    meta = original(name)
    field = '.'.join(path)
    value = meta
    for key in path:
        value = value[key]
    problems = []
    for label, new in variants(value):
        directory = weights_dir(tmp_path, name, mutated(meta, path, new))
        problem = outcome(directory, field)
        if problem is not None:
            problems.append(f'{field} {label} ({str(new)[:40]}): {problem}')
    assert not problems, '\n'.join(problems)


def test_the_fuzz_covers_every_field():
    """The three checkpoints together have every config field and every schema field."""
    seen = {'.'.join(p) for name in SHIPPED for p in leaves(original(name))}
    config = {f'config.{f}' for f in CONFIG_LIMITS}
    assert config <= seen
    assert {'param_names', 'obs_layout.velocity_encoding', 'context.needs_true_param',
            'steps.wall_s', 'run.seed', 'control_timestep'} <= seen


def test_config_limits_cover_every_config_field():
    fields = set(config_types())   # the shared fields and every method's own settings
    assert set(CONFIG_LIMITS) == fields
    assert LATER_CONFIG_KEYS <= fields


@pytest.mark.parametrize('family', list(SIM_FAMILIES))
def test_the_robot_table_is_what_the_real_model_has(family):
    """sim_node.structures is what MuJoCo builds: the controllers check weights against it."""
    env = make_env(family)
    robot = DOMAIN_STRUCTURES[get_sim_family(family).domain]
    assert env.layout.joint_names == robot.joint_names
    assert env.layout.position_encoding == robot.position_encoding
    assert env.layout.velocity_encoding == robot.velocity_encoding
    assert tuple(env.actuator_names) == robot.actuator_names
    assert env.control_timestep == robot.control_timestep


# Files that ended a controller with a traceback (#39): at start, or at the
# policy's first action; accepted silently (estimates NaN); never controlling.
BAD_FILES = {
    'config.hidden_dim': (('config', 'hidden_dim'), 'x'),
    'config.actor_log_std_max': (('config', 'actor_log_std_max'), 'x'),
    'param_normalisation.offset': (('param_normalisation', 'offset'), 1e308),
    'obs_layout.joint_names': (('obs_layout', 'joint_names'),
                               [f'joint_{i}' for i in range(9)]),
}


def test_controllers_started_on_a_bad_file_exit_with_one_line(spawn, tmp_path):
    name = 'walker-walk-v0-zeus'
    good = start_node(spawn, 'policy_node', {'weights': weights_dir(tmp_path / 'good', name,
                                                                    original(name))})
    procs = {}
    for field, (path, value) in BAD_FILES.items():
        directory = weights_dir(tmp_path / field, name, mutated(original(name), path, value))
        for node in ('context_node', 'policy_node'):
            procs[field, node] = start_node(spawn, node, {'weights': directory})
    deadline = time.monotonic() + 240   # torch loads for seconds in each, all at once
    for (field, node), proc in procs.items():
        try:
            code = proc.proc.wait(max(1.0, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            code = 'none: still running'
        output = proc.output()
        refusals = [line for line in output.splitlines() if f': {field}: ' in line]
        assert code == 1, f'{node} on a bad {field}: exit code {code}\n{output}'
        assert 'Traceback' not in output, f'{node} on a bad {field}:\n{output}'
        assert len(refusals) == 1 and refusals[0].startswith(node.title().replace('_', '')), \
            f'{node} on a bad {field}:\n{output}'
    # The same set-up with the file unchanged runs: the refusals above are the file's.
    while f'{FAMILY} weights from' not in good.output():
        assert good.alive() and time.monotonic() < deadline, good.output()
        time.sleep(0.2)
