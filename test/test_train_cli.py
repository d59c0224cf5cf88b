"""The training command line, generated from the config dataclasses; what users type works."""

from dataclasses import fields
from pathlib import Path
import re
import shlex

from conftest import REPO
import pytest

from zeus_ros.learning_tools import train
from zeus_ros.core.config import (config_types, RUN_KEYS, setting_owners, settings_classes,
                                   SHARED_KEYS, ZeusConfig)
from zeus_ros.learning_tools.sweep_config import SweepConfig

pytestmark = pytest.mark.unit


def squeezed(text: str) -> str:
    """Return `text` without whitespace (argparse wraps lines, even inside hyphenated words)."""
    return ''.join(text.split())


def help_text() -> str:
    return squeezed(train.build_parser().format_help())


def parse(argv: list[str]) -> train.RunArgs:
    return train.RunArgs.from_cli(train.build_parser().parse_args(argv))


def option(name: str) -> str:
    return '--' + name.replace('_', '-')


def test_help_names_every_config_field_with_its_help_and_default():
    text = help_text()
    kinds = config_types()
    assert set(kinds) == set(SHARED_KEYS) | set(setting_owners())
    for name in kinds:
        if name in RUN_KEYS:   # the run's own --family, --method, --profile
            continue
        assert option(name) in text, name
    for cls in (ZeusConfig, *settings_classes()):
        for f in fields(cls):
            if 'help' not in f.metadata or f.name in RUN_KEYS:
                continue   # method_settings: its fields are listed; RUN_KEYS: run options
            assert squeezed(f.metadata['help']) in text, f.name
            assert squeezed(f'{option(f.name)}') in text, f.name
            assert squeezed(f'(default: {f.default!r})') in text, f.name


def test_help_names_every_run_option_with_its_default():
    text = help_text()
    for f in fields(train.RunArgs):
        if f.name != 'overrides':
            assert option(f.name) in text, f.name
    assert '--no-save-replay' in text and '(default:10000)' in text


def test_every_config_option_is_an_override_and_wins_over_set():
    args = parse(['--out', 'r', '--method', 'cadm', '--alpha-psi', '0.5', '--backward-weight',
                  '0.25', '--no-context-critic-grad', '--set', 'alpha_psi=0.1',
                  'context_length=7'])
    assert args.overrides == {'alpha_psi': 0.5, 'backward_weight': 0.25,
                              'context_critic_grad': False, 'context_length': 7}
    assert train.family_config('walker-walk-v0', 'cpu', 'cadm', **args.overrides) \
        .method_settings.backward_weight == 0.25


def test_the_run_options_users_type_keep_their_meaning():
    args = parse(['--out', 'runs/x', '--family', 'cheetah-run-v1', '--method', 'up-osi',
                  '--seed', '2', '--steps', '50', '--eval-every', '0', '--eval-episodes', '3',
                  '--eval-max-steps', '20', '--eval-splits', 'train', 'extrapolation',
                  '--checkpoint-every', '25', '--log-every', '5', '--time-limit', '1.5',
                  '--no-save-replay', '--resume', '--quiet', '--set', 'num_threads=1'])
    assert args == train.RunArgs(
        out=Path('runs/x'), family='cheetah-run-v1', method='up-osi', seed=2, steps=50,
        eval_every=0, eval_episodes=3, eval_max_steps=20,
        eval_splits=('train', 'extrapolation'), checkpoint_every=25, log_every=5,
        time_limit=1.5, save_replay=False, resume=True, quiet=True,
        overrides={'num_threads': 1})
    defaults = parse(['--out', 'y'])
    assert defaults == train.RunArgs(out=Path('y')) and defaults.save_replay


@pytest.mark.parametrize('argv, message', [
    (['--set', 'bakward_weight=1'], "unknown config field 'bakward_weight' (did you mean "
                                    "'backward_weight'?)"),
    (['--set', 'nonsense=1'], "unknown config field 'nonsense'"),
    (['--set', 'method=cadm'], '--set method: set it with --method'),
    (['--set', 'alpha_psi'], 'write KEY=VALUE'),
    (['--set', 'context_length=five'], '--set context_length: invalid literal'),
    (['--set', 'backward_weight=0.3'], "backward_weight is a setting of method cadm; method "
                                       "'zeus' does not read it"),
    (['--method', 'sac', '--osi-warmup-updates', '5'], 'a setting of method up-osi'),
    (['--set', 'train_swap_prob=2'], 'train_swap_prob must be in [0, 1]'),
])
def test_a_bad_config_key_or_value_is_refused_with_one_clear_line(argv, message, capsys,
                                                                   tmp_path):
    with pytest.raises(SystemExit) as stop:
        train.main(['--out', str(tmp_path / 'run'), *argv])
    assert stop.value.code == 2
    err = capsys.readouterr().err
    assert message in err and 'Traceback' not in err
    assert not (tmp_path / 'run').exists()   # refused before anything was written


def recorded_commands() -> list[list[str]]:
    """Return the training commands the shipped weights record, and the queue's options."""
    commands = []
    for record in sorted((REPO / 'weights').glob('*/RECORD.md')):
        for found in re.findall(r'python -m zeus_ros\.train ([^`;]+)', record.read_text()):
            commands.append(shlex.split(found))
    assert len(commands) >= 9
    queue = (REPO / 'scripts' / 'run_queue.sh').read_text()
    assert '--quiet --set num_threads=1' in queue
    commands.append(['--out', 'runs/q', '--family', 'walker-walk-v0', '--resume', '--quiet',
                     '--set', 'num_threads=1'])
    return commands


@pytest.mark.parametrize('argv', recorded_commands(), ids=lambda argv: argv[argv.index(
    '--out') + 1] if '--out' in argv else '?')
def test_every_recorded_training_command_still_parses_to_a_valid_config(argv):
    args = parse(argv)
    cfg = train.family_config(args.family, args.profile, args.method, **args.overrides)
    assert cfg.method == args.method
    assert all(cfg.to_dict()[k] == v for k, v in args.overrides.items())


def test_a_sweep_refuses_an_override_one_of_its_methods_does_not_read(tmp_path):
    bad = tmp_path / 'bad.yaml'
    bad.write_text('name: x\nfamilies: [finger-spin-v0]\nmethods: [zeus, cadm]\nseeds: [1]\n'
                   'steps: 5\noverrides: {backward_weight: 0.3}\n')
    with pytest.raises(ValueError, match="overrides: backward_weight is a setting of method "
                                         "cadm; method 'zeus'"):
        SweepConfig.load(bad)
    bad.write_text('name: x\nfamilies: [finger-spin-v0]\nmethods: [cadm]\nseeds: [1]\n'
                   'steps: 5\noverrides: {backward_weight: 0.3}\n')
    assert SweepConfig.load(bad).overrides == {'backward_weight': 0.3}


def test_no_run_option_shadows_a_config_field():
    run = {f.name for f in fields(train.RunArgs)}
    assert run & set(config_types()) == set(RUN_KEYS)
    dests = [a.dest for a in train.build_parser()._actions]
    assert len(dests) == len(set(dests))   # one option per field: none generated twice
