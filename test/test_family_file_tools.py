"""A family file through the tools (#48): train on the Hopper, report on it, the checkpoint.

The Hopper (examples/hopper/, Gymnasium's MJCF) is trained a few hundred steps
through `train --family-file`; the adaptation report then runs on the result
in a fresh process, from a directory where the family file cannot be found:
the checkpoint carries it.
"""

import hashlib
import json
from pathlib import Path
import subprocess
import sys

from conftest import REPO
import pytest
from sim_driver import (assert_same_rewards, collect, episode_rewards, LockstepDriver,
                        start_node)
from zeus_msgs.msg import StepInfo

from sim_node.families import SIM_FAMILIES

from zeus_ros.deploy.inference import InferenceModel
from zeus_ros.deploy.metadata import CheckpointMetadata, MetadataError
from zeus_ros.learning_tools.evaluate import run_episode

pytestmark = pytest.mark.ros   # starts processes of its own

HOPPER = REPO / 'examples' / 'hopper' / 'hopper.yaml'
STEPS = 300


@pytest.fixture(scope='module')
def hopper_run(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp('hopper') / 'run'
    subprocess.run([sys.executable, '-m', 'zeus_ros.learning_tools.train',
                    '--family-file', str(HOPPER), '--steps', str(STEPS), '--out', str(out),
                    '--eval-every', '0', '--checkpoint-every', str(STEPS), '--quiet',
                    '--set', 'init_steps=100', 'hidden_dim=32', 'num_threads=1',
                    'batch_size_per_task=4', 'replay_capacity=2000', 'context_length=5'],
                   check=True, cwd=REPO, capture_output=True)
    return out


def metadata(run: Path) -> dict:
    return json.loads((run / 'checkpoint' / 'metadata.json').read_text())


def test_training_on_a_family_file_records_the_file_in_the_checkpoint(hopper_run):
    meta = metadata(hopper_run)
    recorded = meta['family_file']
    assert meta['family'] == 'hopper-friction-leg' == meta['config']['family']
    assert recorded['text'] == HOPPER.read_text()
    assert recorded['model_xml'] == (HOPPER.parent / 'hopper.xml').read_text()
    assert meta['param_names'] == ['floor_friction', 'leg_length']
    assert meta['steps']['timestep'] == STEPS and meta['run']['family_file'] == str(HOPPER)
    # Four train tasks (2 frictions x 2 lengths), each stepped once per timestep.
    assert meta['steps']['env_steps'] == 4 * STEPS


def test_the_recorded_family_file_round_trips_through_the_schema(hopper_run):
    meta = metadata(hopper_run)
    assert CheckpointMetadata.parse(meta).to_dict() == meta


def test_a_tampered_family_file_in_a_checkpoint_is_refused(hopper_run):
    meta = metadata(hopper_run)
    meta['family_file']['text'] += '\n# edited after training\n'
    with pytest.raises(MetadataError, match='^family_file.sha256: must be the sha256'):
        CheckpointMetadata.parse(meta)
    # Consistent hash, another family's name: refused, and that name is not registered.
    text = meta['family_file']['text'].replace('name: hopper-friction-leg', 'name: hopper-x')
    meta['family_file'].update(text=text, sha256=hashlib.sha256(text.encode()).hexdigest())
    with pytest.raises(MetadataError, match="^family_file.text: declares family 'hopper-x'"):
        CheckpointMetadata.parse(meta)
    assert 'hopper-x' not in SIM_FAMILIES
    meta['family_file']['text'] = text.replace('parameters:', 'colour: red\nparameters:')
    meta['family_file']['sha256'] = hashlib.sha256(
        meta['family_file']['text'].encode()).hexdigest()
    with pytest.raises(MetadataError, match='^family_file: family_file.text: colour: unknown'):
        CheckpointMetadata.parse(meta)


def test_the_adaptation_report_runs_on_it_without_the_file(hopper_run, tmp_path):
    report = tmp_path / 'report.json'
    done = subprocess.run([sys.executable, '-m', 'zeus_ros.learning_tools.adaptation',
                           '--weights', str(hopper_run), '--episodes', '1', '--max-steps', '40',
                           '--swap-step', '20', '--swap-steps', '40', '--no-context-use-train',
                           '--json', str(report)],
                          cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    assert done.stdout.startswith('hopper-friction-leg zeus')
    data = json.loads(report.read_text())
    splits = {r['split'] for r in data['returns']}
    assert splits == {'train', 'interpolation', 'extrapolation'}
    assert set(data['identification']['r2_per_parameter']) == {'floor_friction', 'leg_length'}
    assert data['swaps'], 'a live swap episode per held-out pair'


def bad_file(tmp_path: Path) -> Path:
    path = tmp_path / 'bad.yaml'
    path.write_text(HOPPER.read_text().replace('geom: leg_geom', 'geom: shin_geom'))
    (tmp_path / 'hopper.xml').write_text((HOPPER.parent / 'hopper.xml').read_text())
    return path


@pytest.mark.parametrize('tool, extra', [
    ('zeus_ros.learning_tools.train', ['--out', 'never']),
    ('zeus_ros.learning_tools.adaptation', ['--weights', 'never']),
])
def test_a_bad_family_file_exits_1_with_one_line_and_no_traceback(tmp_path, tool, extra):
    path = bad_file(tmp_path)
    done = subprocess.run([sys.executable, '-m', tool, '--family-file', str(path), *extra],
                          cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert done.returncode == 1
    assert 'Traceback' not in done.stderr and len(done.stderr.strip().splitlines()) == 1
    assert f"{path}: parameters[1].edit.geom: the model has no geom named 'shin_geom'" \
        in done.stderr
    assert not (tmp_path / 'never').exists()


def test_family_check_prints_what_a_controller_will_see(tmp_path):
    done = subprocess.run([sys.executable, '-m', 'zeus_ros.learning_tools.family_check',
                           str(HOPPER)], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert '  parameter leg_length [m] (length): default 0.5, live range [0.25, 0.6]' \
        in done.stdout
    assert '  extrapolation: 4 tasks (0.2, 0.5), (2.8, 0.5), (1, 0.34), (1, 0.58)' in done.stdout
    assert 'observation (12 values)' in done.stdout
    bad = subprocess.run([sys.executable, '-m', 'zeus_ros.learning_tools.family_check',
                          str(bad_file(tmp_path))], cwd=REPO, capture_output=True, text=True,
                         timeout=120)
    assert bad.returncode == 1 and len(bad.stderr.strip().splitlines()) == 1
    assert "parameters[1].edit.geom: the model has no geom named 'shin_geom'" in bad.stderr


def test_the_trained_controllers_run_the_hopper_through_ros_bit_exactly(hopper_run, spawn,
                                                                        ros_node):
    """sim_node (family_file), context_node and policy_node: the in-process episode."""
    weights = hopper_run / 'checkpoint'
    model = InferenceModel.load(weights)
    values, seed = (1.0, 0.58), 3          # an extrapolation length
    expected = run_episode(model, model.family, values, seed)
    steps = collect(ros_node, StepInfo, '/zeus/step')
    start_node(spawn, 'sim_node', {'family_file': str(HOPPER), 'command_timeout': 5.0})
    start_node(spawn, 'context_node', {'weights': weights})
    start_node(spawn, 'policy_node', {'weights': weights, 'context_timeout': 5.0})
    driver = LockstepDriver(ros_node)
    driver.wait_ready()
    rewards = episode_rewards(ros_node, driver, steps, seed, length=len(expected.rewards),
                              params=dict(zip(model.param_names, values, strict=True)))
    assert_same_rewards(rewards, expected.rewards)


def test_bringup_passes_the_family_file_to_the_sim_and_asks_for_it(hopper_run):
    from zeus_ros.ros_tools.bringup import node_parameters, parse_args
    weights = str(hopper_run / 'checkpoint')
    params = node_parameters(parse_args(['--weights', weights, '--family-file', str(HOPPER),
                                         '--param', 'leg_length=0.3']))
    sim = params['sim_node']
    assert sim['family_file'] == str(HOPPER.resolve()) and sim['leg_length'] == 0.3
    assert sim['family'] == 'hopper-friction-leg'
    with pytest.raises(SystemExit, match='trained on a family file .* give it with '
                                         '--family-file'):
        node_parameters(parse_args(['--weights', weights]))


def test_the_your_robot_page_shows_what_family_check_prints():
    """The docs page quotes the command's output: it must stay what the command prints."""
    done = subprocess.run([sys.executable, '-m', 'zeus_ros.learning_tools.family_check',
                           'examples/hopper/hopper.yaml'], cwd=REPO, capture_output=True,
                          text=True, timeout=120)
    page = (REPO / 'docs' / 'pages' / 'your-robot.md').read_text()
    assert '$ python -m zeus_ros.learning_tools.family_check examples/hopper/hopper.yaml' in page
    assert [line for line in done.stdout.splitlines() if line not in page] == []
