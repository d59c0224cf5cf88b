"""metadata.json is one typed tree (zeus_ros.deploy.metadata): parsed and written in one place.

Every checkpoint this repository ships or records loads, and parsing then
serialising gives back its file byte for byte: optional keys an old file
left out stay out, keys the schema does not know are kept.
"""

from dataclasses import replace
import json

from conftest import REPO
import pytest

from zeus_ros.deploy.checkpoint import load_metadata, METADATA_FILE
from zeus_ros.deploy.metadata import CheckpointMetadata, MetadataError

# Every shipped weights folder and every recorded run's checkpoint.
SHIPPED = sorted(p.parent for p in (*(REPO / 'weights').glob(f'*/{METADATA_FILE}'),
                                    *(REPO / 'research' / 'results').rglob(METADATA_FILE)))
WALKER = REPO / 'weights' / 'walker-walk-v0-zeus'


def raw(folder) -> dict:
    return json.loads((folder / METADATA_FILE).read_text())


def test_there_are_shipped_checkpoints_to_check():
    assert len([p for p in SHIPPED if p.parent.name == 'weights']) >= 10
    assert len(SHIPPED) >= 50


@pytest.mark.parametrize('folder', SHIPPED, ids=lambda p: str(p.relative_to(REPO)))
def test_every_shipped_metadata_loads_and_writes_back_byte_for_byte(folder):
    meta = load_metadata(folder)
    assert meta.to_json() == (folder / METADATA_FILE).read_text()
    assert CheckpointMetadata.parse(meta.to_dict()) == meta


def test_an_old_file_keeps_its_missing_optional_keys_missing():
    # walker-walk-v0-zeus predates the method plug-ins and the reward entry.
    old = raw(WALKER)
    assert 'method' not in old['context'] and 'reward_in_observation' not in old['obs_layout']
    meta = CheckpointMetadata.parse(old)
    assert meta.context.method == 'zeus' and meta.obs_layout.reward_in_observation is False
    assert meta.to_dict() == old


def test_a_changed_optional_value_is_written_even_where_the_file_had_none():
    meta = CheckpointMetadata.parse(raw(WALKER))
    wall = replace(meta, steps=replace(meta.steps, wall_s=12.5))
    assert 'wall_s' not in raw(WALKER)['steps'] and wall.to_dict()['steps']['wall_s'] == 12.5


def test_keys_the_schema_does_not_know_are_kept_at_every_level():
    newer = raw(WALKER)
    newer['note'] = 'from a newer writer'
    newer['obs_layout']['units'] = ['m', 'rad']
    meta = CheckpointMetadata.parse(newer)
    assert meta.extra == {'note': 'from a newer writer'}
    assert meta.obs_layout.extra == {'units': ['m', 'rad']}
    assert meta.to_json() == json.dumps(newer, indent=2, sort_keys=True)


def test_a_sawyer_checkpoint_carries_its_dropped_velocities():
    # The commanded gripper position has no velocity: the layout must say so.
    from sim_node.sawyer import LAYOUT
    sawyer = REPO / 'weights' / 'sawyer-peg-v0-zeus'
    assert load_metadata(sawyer).obs_layout.layout() == LAYOUT
    without = raw(sawyer)
    del without['obs_layout']['velocity_encoding']   # read as "all kept": not this robot
    with pytest.raises(MetadataError, match=r'^obs_layout\.velocity_encoding: '):
        CheckpointMetadata.parse(without)


def test_a_newer_format_is_refused_by_name():
    newer = dict(raw(WALKER), format_version=2)
    with pytest.raises(MetadataError, match='^format_version: checkpoint format 2, this code '
                                            'reads 1$'):
        CheckpointMetadata.parse(newer)


CHEETAH_RMA = REPO / 'weights' / 'cheetah-run-wide-friction-rma-raw-150k'


def test_actuator_units_are_optional_and_round_trip():
    # Checkpoints from before #49 carry no control range or gear and still load.
    old = raw(CHEETAH_RMA)
    assert 'gear' not in old['action_layout']
    assert CheckpointMetadata.parse(old).action_layout.gear is None
    newer = raw(CHEETAH_RMA)
    newer['action_layout'].update(ctrl_low=[-1.0] * 6, ctrl_high=[1.0] * 6,
                                  gear=[120.0, 90.0, 60.0, 90.0, 60.0, 30.0])
    meta = CheckpointMetadata.parse(newer)
    assert meta.action_layout.gear[0] == 120.0
    assert meta.to_json() == json.dumps(newer, indent=2, sort_keys=True)


@pytest.mark.parametrize('change, field', [
    (dict(gear=[1.0] * 6), 'gear'),                                          # alone
    (dict(ctrl_low=[-1.0] * 6, ctrl_high=[1.0] * 6, gear=[1.0] * 5), 'gear'),  # one short
    (dict(ctrl_low=[1.0] * 6, ctrl_high=[-1.0] * 6, gear=[1.0] * 6), 'ctrl_high'),
])
def test_inconsistent_actuator_units_are_refused_by_name(change, field):
    bad = raw(CHEETAH_RMA)
    bad['action_layout'].update(change)
    with pytest.raises(MetadataError, match=rf'^action_layout\.{field}: '):
        CheckpointMetadata.parse(bad)


def test_the_trainer_records_the_units_of_its_env():
    from sim_node.env import make_env
    from zeus_ros.learning_tools.train import env_info
    info = env_info(make_env('cheetah-run-wide-friction'))
    assert info['actuator_units'][2] == (120.0, 90.0, 60.0, 90.0, 60.0, 30.0)
