"""What each domain's robot exposes to a controller, as a table: MuJoCo-free.

A checkpoint's metadata names the joints, their encodings, the actuators and
the control period the weights were trained with. The controller nodes check
them against the family BEFORE anything is built (zeus_ros.deploy.metadata),
in a process that never loads MuJoCo, so the facts are written out here;
test/test_metadata_fuzz.py asserts that every family's real model (sim_node.env
for the dm_control domains, sim_node.sawyer) gives exactly these.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class DomainStructure:
    """Joints (model order), their observation encodings, actuators, control period."""

    joint_names: tuple[str, ...]
    position_encoding: tuple[str, ...]    # 'raw', 'angle' or 'drop' (sim_node.layout)
    velocity_encoding: tuple[str, ...] | None   # None: every velocity observed
    actuator_names: tuple[str, ...]
    control_timestep: float               # s


_WALKER_LEGS = ('right_hip', 'right_knee', 'right_ankle', 'left_hip', 'left_knee', 'left_ankle')
_CHEETAH_LEGS = ('bthigh', 'bshin', 'bfoot', 'fthigh', 'fshin', 'ffoot')
_SAWYER_ENTRIES = (tuple(f'right_j{i}' for i in range(7)) + ('r_close', 'l_close')
                   + tuple(f'{part}{a}' for part in ('hand_', 'hand_target_', 'peg_', 'peg_q')
                           for a in 'xyz'))

DOMAIN_STRUCTURES: dict[str, DomainStructure] = {
    'walker': DomainStructure(('rootz', 'rootx', 'rooty') + _WALKER_LEGS,
                              ('raw', 'drop', 'angle') + ('raw',) * 6, None, _WALKER_LEGS,
                              0.025),
    'cheetah': DomainStructure(('rootx', 'rootz', 'rooty') + _CHEETAH_LEGS,
                               ('drop', 'raw', 'angle') + ('raw',) * 6, None, _CHEETAH_LEGS,
                               0.01),
    'finger': DomainStructure(('proximal', 'distal', 'hinge'), ('raw', 'raw', 'angle'), None,
                              ('proximal', 'distal'), 0.02),
    'cartpole': DomainStructure(('slider', 'hinge_1'), ('raw', 'angle'), None, ('slide',),
                                0.01),
    'reacher': DomainStructure(('shoulder', 'wrist', 'target_x', 'target_y'),
                               ('angle', 'raw', 'raw', 'raw'), None, ('shoulder', 'wrist'),
                               0.02),
    # The commanded hand position persists between steps: no velocity of its own.
    'sawyer': DomainStructure(_SAWYER_ENTRIES, ('raw',) * len(_SAWYER_ENTRIES),
                              tuple('drop' if e.startswith('hand_target_') else 'raw'
                                    for e in _SAWYER_ENTRIES),
                              ('hand_dx', 'hand_dy', 'hand_dz', 'gripper'), 0.05),
}
