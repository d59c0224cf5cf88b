"""Check a family file against its model and say what a controller of it will see.

    python -m zeus_ros.learning_tools.family_check examples/hopper/hopper.yaml

Loads the file as the trainer and the sim node do (schema, values, the MJCF
compiled with every name it uses looked up), then prints the family: its
parameters with their ranges and splits, the observed joints and the
actuators. A file that cannot be used: one line naming the file and the
field, exit status 1.
"""

from __future__ import annotations

import argparse
import sys

from sim_node.env import make_env
from sim_node.family_edits import load_family_file
from sim_node.family_file import FamilyFileError, FileFamilySpec


def describe(spec: FileFamilySpec) -> list[str]:
    """Return the lines `family_check` prints for a loaded family."""
    env = make_env(spec.name, None, seed=0)
    lines = [f'{spec.name}: {spec.description}'.rstrip(': '),
             f'  model {spec.document.model.mjcf}, control period {env.control_timestep:g} s, '
             f'horizon {env.episode_steps} steps']
    for param in spec.document.parameters:
        lo, hi = param.live_range
        lines.append(f'  parameter {param.name} [{param.unit or "-"}] ({param.edit.kind}): '
                     f'default {param.default:g}, live range [{lo:g}, {hi:g}]')
    for split in ('train', 'interpolation', 'extrapolation'):
        tasks = spec.split(split)
        shown = ', '.join('(' + ', '.join(f'{v:.4g}' for v in task) + ')' for task in tasks)
        lines.append(f'  {split}: {len(tasks)} tasks {shown}')
    lines.append(f'  observation ({env.obs_dim} values): joints {", ".join(env.joint_names)}')
    lines.append(f'  actions ({env.action_dim}): {", ".join(env.actuator_names)}')
    return lines


def main(argv: list[str] | None = None) -> int:
    """Console entry point (`family_check`)."""
    parser = argparse.ArgumentParser(prog='family_check', description=__doc__.split('\n')[0])
    parser.add_argument('family_file', help='the family file (YAML)')
    args = parser.parse_args(argv)
    try:
        spec = load_family_file(args.family_file)
    except FamilyFileError as error:
        print(f'family_check: {error}', file=sys.stderr)
        return 1
    print('\n'.join(describe(spec)))
    return 0


if __name__ == '__main__':
    sys.exit(main())
