r"""Measure whether zeus-id's context reads cheetah-run-v1's target velocity, or only its sign.

The reward of cheetah-run-v1 is r = -|v - T| - 0.05 |a|^2 with v the speed
after the step. Knowing a, one transition gives d = |v - T|, so T = v + d or
v - d: the target is identified only up to a mirror about the speed, and a
window separates the two only as far as its speeds vary. This script runs
each checkpoint exactly as the evaluator does (`zeus_ros.learning_tools.evaluate.run_episode`,
`InferenceModel`, the evaluator's episode seeds 0 and 1, 1000 steps) at every
interpolation target, with the deterministic policy tanh(mu) and with actions
sampled from the same actor (`Actor.sample`, the trainer's collection policy).
Per control step it records the true target T, the speed v, d read from the
reward, and the decoded estimate; per window (the k transitions psi read)
the mean speed vbar, the mean d (dbar), the spread of v, and the two roots
vbar + dbar ("upper") and vbar - dbar ("lower"): one of them is T, the other
the mirror 2 vbar - T.

A second measure relabels rewards: the same windows (states and actions of
the deterministic and of the sampled episodes) are given the rewards they
would have earned under another target T' (0 to 3 m/s; the dynamics do not
depend on T, so such a window is one the family can produce) and decoded.
If the encoder reads the reward but cannot tell the sign, its estimate
follows vbar + |vbar - T'| (or vbar - |vbar - T'|) rather than T'.

    cd /work/main && source scripts/ros_env.sh && source .venv/bin/activate
    PYTHONPATH=. OMP_NUM_THREADS=1 nice -n 8 \
        python research/analysis/target_velocity_identifiability.py \
        --runs /work/runs/cv1-zeus-id-s1 /work/runs/cv1-zeus-id-s2 /work/runs/cv1-zeus-id-s3

About 4 CPU-minutes for three checkpoints. Writes
research/results/target_velocity_identifiability.md and .csv (per seed, policy
and target).
"""

from __future__ import annotations

import argparse
import csv
from pathlib import Path
import time

import numpy as np
import torch

from sim_node.env import ParamEnv
from zeus_ros.learning_tools.adaptation import r_squared, SpeedRecorder
from zeus_ros.core.window import ContextWindow
from zeus_ros.deploy.inference import InferenceModel
from zeus_ros.learning_tools.evaluate import run_episode

RESULTS = Path(__file__).resolve().parents[1] / 'results'
NAME = 'target_velocity_identifiability'
CONTROL_COST = 0.05
WRONG = 0.25          # m/s: an estimate farther than this from T counts as wrong
RELABEL_TARGETS = tuple(np.round(np.arange(0.0, 3.01, 0.25), 2))
RELABEL_EVERY = 25    # steps between relabelled windows (episode seed 0 only)
POLICIES = ('deterministic', 'sampled')
REPLAY_LIKE = ('sampled', 'random')   # at the train targets: the replay's two sources


class SampledActions:
    """The deployed model with actions sampled from its actor instead of tanh(mu).

    Everything else (features, context, decoder) is the loaded model's own.
    """

    def __init__(self, model: InferenceModel):
        self._model = model

    def __getattr__(self, name):
        return getattr(self._model, name)

    @torch.no_grad()
    def act(self, obs, latent):
        """Sample tanh(mu + sigma * noise) from the checkpoint's actor."""
        features = torch.from_numpy(self._model.features(obs))[None]
        latent = torch.from_numpy(np.asarray(latent, np.float32).reshape(1, -1))
        action, _, _ = self._model.actor.sample(torch.cat([features, latent], dim=-1))
        return action[0].numpy().astype(np.float64)


class RandomActions(SampledActions):
    """The deployed model acting uniformly at random (the trainer's first 10000 timesteps)."""

    def __init__(self, model: InferenceModel, seed: int):
        super().__init__(model)
        self._rng = np.random.RandomState(seed)

    def act(self, obs, latent):  # noqa: ARG002 (the policy it stands in for reads them)
        """Draw a uniform action in [-1, 1]."""
        return self._rng.uniform(-1.0, 1.0, self._model.action_dim)


def run(model: InferenceModel, policy: str, target: float, seed: int, max_steps: int):
    """One episode; return the per-step record and the speed after every step."""
    recorder = SpeedRecorder()
    if policy == 'sampled':
        torch.manual_seed(10_000 + seed)
        actor = SampledActions(model)
    elif policy == 'random':
        actor = RandomActions(model, 10_000 + seed)
    else:
        actor = model
    rec = run_episode(actor, model.family, target, seed, max_steps=max_steps, probe=recorder)
    return rec, np.asarray(recorder.speeds)


def window_rows(model: InferenceModel, rec, speeds, costs, t: int, target: float):
    """Window psi reads at step t, its rewards recomputed for `target` (ContextWindow's rows)."""
    window = ContextWindow(model.k, model.obs_dim, model.action_dim)
    for i in range(t - model.k, t):
        reward = -abs(speeds[i] - target) - costs[i]
        window.push(rec.observations[i], rec.actions[i], reward, rec.observations[i + 1])
    return window.arrays()


def step_table(model, rec, speeds, target: float) -> dict:
    """Per-step arrays for the steps whose window is full (t >= k)."""
    k = model.k
    costs = CONTROL_COST * np.sum(np.clip(rec.actions, -1, 1) ** 2, axis=1)
    d = -rec.rewards - costs   # = |v - T|: the reward less the known control cost
    n = min(len(rec.rewards), len(speeds))
    steps = np.arange(k, n)
    vbar = np.array([speeds[t - k:t].mean() for t in steps])
    dbar = np.array([d[t - k:t].mean() for t in steps])
    spread = np.array([speeds[t - k:t].std() for t in steps])
    vrange = np.array([np.ptp(speeds[t - k:t]) for t in steps])
    return {'t': steps, 'target': np.full(steps.size, target), 'v': speeds[steps],
            'd': d[steps], 'd_check': np.abs(np.abs(speeds[:n] - target) - d[:n]).max(),
            'estimate': rec.estimates[steps], 'vbar': vbar, 'dbar': dbar,
            'spread': spread, 'range': vrange, 'costs': costs}


def relabel(model, rec, speeds, costs) -> list[dict]:
    """Decode the episode's windows with rewards recomputed for every relabel target."""
    out = []
    k = model.k
    n = min(len(rec.rewards), len(speeds))
    for t in range(k, n, RELABEL_EVERY):
        vbar = float(speeds[t - k:t].mean())
        spread = float(speeds[t - k:t].std())
        for other in RELABEL_TARGETS:
            rows, mask = window_rows(model, rec, speeds, costs, t, float(other))
            estimate = model.decode(model.context(rows, mask))
            out.append({'t': t, 'relabel': float(other), 'vbar': vbar, 'spread': spread,
                        'estimate': estimate})
    return out


def last_decoder_loss(weights: str) -> float | None:
    """Return the decoder loss of the training log's last row (replay batches), if any."""
    log = Path(weights) / 'train_log.csv'
    if not log.exists():
        return None
    with open(log) as f:
        rows = [r for r in csv.DictReader(f) if r.get('decoder_loss')]
    return float(rows[-1]['decoder_loss']) if rows else None


def measure(weights: str, episodes: int, max_steps: int) -> dict:
    """Every episode of one checkpoint: per-step tables and relabelled windows."""
    model = InferenceModel.load(weights)
    spec = ParamEnv(model.family, seed=0).spec
    targets = spec.interpolation
    data = {'k': model.k, 'method': model.method_name, 'targets': targets, 'steps': {},
            'relabel': {}, 'check': 0.0, 'scale': model.param_scale, 'train': {},
            'decoder_loss': last_decoder_loss(weights)}
    for policy in REPLAY_LIKE:
        for target in spec.train:
            rec, speeds = run(model, policy, target, 0, max_steps)
            data['train'][policy, target] = step_table(model, rec, speeds, target)
    for policy in POLICIES:
        for target in targets:
            for seed in range(episodes):
                rec, speeds = run(model, policy, target, seed, max_steps)
                table = step_table(model, rec, speeds, target)
                if policy == 'deterministic' and seed == 0:
                    # The windows rebuilt here are the ones the episode's context read.
                    rows, mask = window_rows(model, rec, speeds, table['costs'], model.k,
                                             target)
                    assert np.array_equal(model.context(rows, mask), rec.latents[model.k])
                data['check'] = max(data['check'], float(table['d_check']))
                data['steps'][policy, target, seed] = table
                if seed == 0:
                    data['relabel'][policy, target] = relabel(model, rec, speeds,
                                                              table['costs'])
    return data


# -- summaries -------------------------------------------------------------------
def _cat(tables, key):
    return np.concatenate([t[key] for t in tables])


def summarise(tables) -> dict:
    """Figures over the full-window steps of some episodes."""
    T, v, est = _cat(tables, 'target'), _cat(tables, 'v'), _cat(tables, 'estimate')
    vbar, dbar = _cat(tables, 'vbar'), _cat(tables, 'dbar')
    upper, lower = vbar + dbar, vbar - dbar
    mirror = 2 * vbar - T
    wrong = np.abs(est - T) > WRONG
    closer_mirror = np.abs(est - mirror) < np.abs(est - T)
    return {
        'steps': int(T.size), 'mean_speed': float(v.mean()),
        'speed_error': float(np.abs(v - T).mean()),
        'frac_over': float(np.mean(v > T)),
        'mean_estimate': float(est.mean()), 'estimate_sd': float(est.std()),
        'est_error': float(np.abs(est - T).mean()),
        'frac_wrong': float(wrong.mean()),
        'wrong_near_mirror': float(closer_mirror[wrong].mean()) if wrong.any() else np.nan,
        'err_to_mirror_wrong': float(np.abs(est - mirror)[wrong].mean())
        if wrong.any() else np.nan,
        'frac_upper': float(np.mean(np.abs(est - upper) < np.abs(est - lower))),
        'window_sd': float(_cat(tables, 'spread').mean()),
        'window_range': float(_cat(tables, 'range').mean()),
        'mirror_gap': float(np.abs(mirror - T).mean()),
    }


def sign_weights(tables) -> dict:
    """Fit est = a + b vbar + c dbar on windows below and above T: c is the sign read.

    Identified: c = +1 below the target, -1 above; a prior "T = v + d": +1 on
    both sides; the sign unread (the mean of the two roots): c = 0.
    """
    T, est = _cat(tables, 'target'), _cat(tables, 'estimate')
    vbar, dbar = _cat(tables, 'vbar'), _cat(tables, 'dbar')
    out = {}
    for side, sel in (('under', vbar < T), ('over', vbar > T)):
        if sel.sum() < 50:
            out[side] = (np.nan, np.nan)
            continue
        x = np.stack([np.ones(sel.sum()), vbar[sel], dbar[sel]], axis=1)
        coef = np.linalg.lstsq(x, est[sel], rcond=None)[0]
        out[side] = (float(coef[1]), float(coef[2]))
    return out


def normalised_mse(tables, scale: float) -> float:
    """Return the MSE of the estimate for T in decoder-loss units (over the train range)."""
    T, est = _cat(tables, 'target'), _cat(tables, 'estimate')
    return float(np.mean(((est - T) / scale) ** 2))


def r2_against(tables) -> dict:
    """R^2 of the estimate for T, for the upper and lower roots and for the window speed."""
    T, est = _cat(tables, 'target'), _cat(tables, 'estimate')
    vbar, dbar = _cat(tables, 'vbar'), _cat(tables, 'dbar')
    return {'T': r_squared(T, est), 'upper': r_squared(vbar + dbar, est),
            'lower': r_squared(vbar - dbar, est), 'vbar': r_squared(vbar, est)}


def relabel_summary(rows) -> dict:
    """Estimate error for relabel targets above / below the window's speed, and R^2s."""
    T = np.array([r['relabel'] for r in rows])
    est = np.array([r['estimate'] for r in rows])
    vbar = np.array([r['vbar'] for r in rows])
    above = T > vbar + WRONG
    below = T < vbar - WRONG
    upper, lower = vbar + np.abs(vbar - T), vbar - np.abs(vbar - T)
    return {'n': int(T.size),
            'err_above': float(np.abs(est - T)[above].mean()) if above.any() else np.nan,
            'err_below': float(np.abs(est - T)[below].mean()) if below.any() else np.nan,
            'n_above': int(above.sum()), 'n_below': int(below.sum()),
            'below_near_upper': float(np.mean(np.abs(est - upper)[below]
                                              < np.abs(est - T)[below]))
            if below.any() else np.nan,
            'r2_T': r_squared(T, est), 'r2_upper': r_squared(upper, est),
            'r2_lower': r_squared(lower, est)}


def _f(x, digits=2):
    return 'n/a' if x is None or (isinstance(x, float) and np.isnan(x)) else f'{x:.{digits}f}'


# -- report -------------------------------------------------------------------------
def render(all_data: dict, runs: list[str], name: str = NAME) -> tuple[list[str], list[dict]]:
    """Markdown lines and CSV rows."""
    summary_rows, csv_rows = _summaries(all_data, runs)
    lines = [*_header_section(all_data, runs), *_per_seed_section(summary_rows),
             *_root_section(all_data, runs), *_replay_section(all_data, runs),
             *_relabel_section(summary_rows),
             *_per_target_section(all_data, runs, csv_rows, name)]
    return lines, csv_rows


def _summaries(all_data: dict, runs: list[str]) -> tuple[list[tuple], list[dict]]:
    """Per run and policy (name, policy, summary, R^2, relabelled); CSV rows per target."""
    summary_rows, csv_rows = [], []
    for run in runs:
        data = all_data[run]
        seed_name = Path(run).name
        for policy in POLICIES:
            tables = _policy_tables(data, policy)
            s, r2 = summarise(tables), r2_against(tables)
            rel = relabel_summary([row for (p, _), rows in data['relabel'].items()
                                   if p == policy for row in rows])
            summary_rows.append((seed_name, policy, s, r2, rel))
            for target in data['targets']:
                per = summarise([t for (p, v, _), t in data['steps'].items()
                                 if p == policy and v == target])
                csv_rows.append({'run': seed_name, 'policy': policy, 'target': target,
                                 **{k: round(v, 4) if isinstance(v, float) else v
                                    for k, v in per.items()}})
    return summary_rows, csv_rows


def _policy_tables(data: dict, policy: str) -> list[dict]:
    """Return the step tables of every interpolation episode run with `policy`."""
    return [t for (p, _, _), t in data['steps'].items() if p == policy]


def _header_section(all_data: dict, runs: list[str]) -> list[str]:
    methods = ', '.join(sorted({all_data[r].get('method', 'zeus-id') for r in runs}))
    ks = ', '.join(str(k) for k in sorted({all_data[r]['k'] for r in runs}))
    return ['# Target velocity from rewards: identified up to its sign? (cheetah-run-v1, '
            f'{methods})', '',
            'Command and method: the docstring of '
            '`research/analysis/target_velocity_identifiability.py`. Checkpoints: '
            + ', '.join(f'`{r}`' for r in runs) + '. Every interpolation target '
            "(0.4 ... 2.9 m/s), episode seeds 0 and 1 (the evaluator's), 1000 steps, "
            f'k = {ks}; figures over the steps whose window is full. d read from the reward '
            f'equals |v - T| to {all_data[runs[0]]["check"]:.1e} m/s (largest deviation '
            'over the episodes of the first checkpoint).', '',
            '`deterministic`: tanh(mu), what the evaluator and the adaptation report '
            "run. `sampled`: actions sampled from the same actor (the trainer's "
            'collection policy, so windows like those of the replay). '
            f'Wrong: |estimate - T| > {WRONG} m/s. Mirror: 2 vbar - T, vbar the mean speed '
            'of the window psi read. Upper / lower root: vbar + dbar / vbar - dbar (one of '
            'them is T, the other the mirror; "upper" is T when the policy runs below '
            'the target).', '']


def _per_seed_section(summary_rows: list[tuple]) -> list[str]:
    lines = ['## Per seed and policy (all interpolation targets)', '',
             '| run | policy | mean \\|v - T\\| | steps v > T | speed sd in window (m/s) '
             '| \\|mirror - T\\| | est. R^2 for T | R^2 for upper root | R^2 for lower root '
             '| R^2 for vbar | mean \\|est - T\\| | wrong | wrong nearer mirror '
             '| nearer upper root |',
             '|' + '---|' * 14]
    for seed_name, policy, s, r2, _ in summary_rows:
        lines.append(f'| {seed_name} | {policy} | {_f(s["speed_error"])} | '
                     f'{s["frac_over"]:.0%} | {_f(s["window_sd"], 3)} | {_f(s["mirror_gap"])} | '
                     f'{_f(r2["T"])} | {_f(r2["upper"])} | {_f(r2["lower"])} | '
                     f'{_f(r2["vbar"])} | {_f(s["est_error"])} | {s["frac_wrong"]:.0%} | '
                     f'{_f(s["wrong_near_mirror"] * 100, 0)} % | {s["frac_upper"]:.0%} |')
    return lines


def _root_section(all_data: dict, runs: list[str]) -> list[str]:
    lines = ['', '## Which root the estimate takes', '',
             'Least squares est = a + b vbar + c dbar over the windows whose mean speed is '
             'below the target and over those above it. Identified: c = +1 below and -1 '
             'above; a prior "T = v + d": +1 on both sides; sign not read: c near 0 on both '
             '(the mean of the two roots). Blank: fewer than 50 such windows.', '',
             '| run | policy | below T: b | below T: c | above T: b | above T: c |',
             '|' + '---|' * 6]
    for run in runs:
        for policy in POLICIES:
            tables = _policy_tables(all_data[run], policy)
            w = sign_weights(tables)
            lines.append(f'| {Path(run).name} | {policy} | {_f(w["under"][0])} | '
                         f'{_f(w["under"][1])} | {_f(w["over"][0])} | {_f(w["over"][1])} |')
    return lines


def _replay_section(all_data: dict, runs: list[str]) -> list[str]:
    lines = ['', '## Replay-like windows', '',
             "The replay holds every transition of the run (capacity 400k = the run's "
             '400k environment steps), the first 80k from uniform random actions (10000 '
             'timesteps x 8 train tasks). Here: one episode (seed 0) per TRAIN target with '
             "the actor's sampled actions and with uniform random actions, against the "
             "interpolation episodes above. MSE in the decoder loss's units (estimate and "
             'target divided by the train range, 3 m/s); the last decoder loss of the '
             'training log (replay batches) for comparison.', '',
             '| run | decoder loss in training (replay) | interp., deterministic: MSE / R^2 '
             '| train targets, sampled: MSE / R^2 / steps v > T | train targets, random '
             'actions: MSE / R^2 / steps v > T / speed sd in window |', '|' + '---|' * 5]
    for run in runs:
        data = all_data[run]
        interp = [t for (p, _, _), t in data['steps'].items() if p == 'deterministic']
        cells = [_replay_cell(data, policy) for policy in REPLAY_LIKE]
        lines.append(f'| {Path(run).name} | {_f(data.get("decoder_loss"), 3)} | '
                     f'{normalised_mse(interp, data["scale"]):.3f} / '
                     f'{_f(r2_against(interp)["T"])} | ' + ' | '.join(cells) + ' |')
    return lines


def _replay_cell(data: dict, policy: str) -> str:
    tables = [t for (p, _), t in data['train'].items() if p == policy]
    sm = summarise(tables)
    cell = (f'{normalised_mse(tables, data["scale"]):.3f} / {_f(r2_against(tables)["T"])} / '
            f'{sm["frac_over"]:.0%}')
    return cell + (f' / {_f(sm["window_sd"], 3)}' if policy == 'random' else '')


def _relabel_section(summary_rows: list[tuple]) -> list[str]:
    lines = ['', "## Relabelled rewards (same windows, rewards recomputed for T' = 0, 0.25, "
             '..., 3 m/s)', '',
             f'Windows every {RELABEL_EVERY} steps of episode seed 0 at every target. '
             "Above / below: T' more than 0.25 m/s above / below the window's mean speed.",
             '', "| run | policy | windows x T' | mean \\|est - T'\\|, T' above vbar "
             "| same, T' below vbar | below: estimate nearer the upper root "
             "| R^2 for T' | for upper root | for lower root |", '|' + '---|' * 9]
    for seed_name, policy, _, _, rel in summary_rows:
        lines.append(f'| {seed_name} | {policy} | {rel["n"]} | {_f(rel["err_above"])} '
                     f'({rel["n_above"]}) | {_f(rel["err_below"])} ({rel["n_below"]}) | '
                     f'{_f(rel["below_near_upper"] * 100, 0)} % | {_f(rel["r2_T"])} | '
                     f'{_f(rel["r2_upper"])} | {_f(rel["r2_lower"])} |')
    return lines


def _per_target_section(all_data: dict, runs: list[str], csv_rows: list[dict],
                        name: str) -> list[str]:
    lines = ['', '## Per target', '', f'CSV: `{name}.csv` (same columns and more).', '']
    for run in runs:
        seed_name = Path(run).name
        lines += [f'### {seed_name}', '',
                  '| policy | T | mean v | steps v > T | mean estimate (sd) | mean 2 vbar - T '
                  '| wrong | wrong nearer mirror | nearer upper root | speed sd in window |',
                  '|' + '---|' * 10]
        lines += [_per_target_row(all_data[run], row) for row in csv_rows
                  if row['run'] == seed_name]
        lines.append('')
    return lines


def _per_target_row(data: dict, row: dict) -> str:
    tables = [t for (p, v, _), t in data['steps'].items()
              if p == row['policy'] and v == row['target']]
    per = summarise(tables)
    mirror = np.mean(np.concatenate([2 * t['vbar'] - t['target'] for t in tables]))
    return (f'| {row["policy"]} | {row["target"]:g} | {_f(per["mean_speed"])} | '
            f'{per["frac_over"]:.0%} | {_f(per["mean_estimate"])} '
            f'({_f(per["estimate_sd"])}) | {_f(mirror)} | '
            f'{per["frac_wrong"]:.0%} | '
            f'{_f(per["wrong_near_mirror"] * 100, 0)} % | '
            f'{per["frac_upper"]:.0%} | {_f(per["window_sd"], 3)} |')


# Written from the results of the three checkpoints named in the docstring (final, 50k
# timesteps); a re-run on other checkpoints prints the tables with this text unchanged.
CONCLUSION = """\
**The data support the sign ambiguity, not the out-of-distribution explanation.**

* Deterministic and sampled episodes give the same figures in every table (R^2 0.66 / 0.66,
  -0.03 / -0.01, 0.95 / 0.95; speed sd in a window 0.14 / 0.14, 0.25 / 0.23, 0.09 / 0.11
  m/s): at alpha 0.019 the sampled policy is the deterministic one plus little noise, so the
  deterministic episodes are not outside what the current policy collects. Exploration at
  deployment, as SAC samples it, would not help.
* Every encoder reads the target as "v + d" (the upper root). Below the target the
  estimate adds d (c = 0.72-1.02); above it, where T = v - d, no seed subtracts it (c = 0.47,
  0.06 / 0.24, 0.31 instead of -1). With the same windows relabelled for targets below the
  window's speed, the error is 1.06-1.18 m/s in all seeds (0.14-0.54 for targets above),
  and 59-94 % of these estimates are nearer the mirror 2 vbar - T than the truth.
* Which seed "identifies" follows from where its policy runs: seed 3's policy never
  overshoots (0 % of steps v > T; its mean speed is at most 1.17 m/s), so the upper root is
  always the target: R^2 0.95, yet the worst speed error (1.03 m/s). Seed 1 overshoots on
  23 % of the steps (targets 1.11-1.83): R^2 0.66, and its estimate follows its own window
  speed even better (R^2 0.84 against vbar). Seed 2 runs at 1.5-1.9 m/s whatever the target,
  above it on 53 % of the steps; at targets 0.4-1.11 (85-98 % above) 66-81 % of its wrong
  estimates are nearer the mirror; its mean estimate per target is 1.66-2.19 m/s (R^2
  -0.03): stuck.
* Seed 2's low replay loss (0.021) fits the replay's composition: on uniform-random windows
  (the first 80k of its 400k transitions; the cheetah barely moves, v < T on 98 % of the
  steps) its decoder MSE is 0.002 (R^2 0.98), on its current policy's windows at the train
  targets 0.108 (R^2 -0.01). (The older policy data in between is not measured here.)
* The windows do carry the sign: speeds vary by 0.09-0.25 m/s (sd) within 25 steps, and
  across a window d changes with v with slope +1 above the target and -1 below. A mean of
  per-transition codes does not pick this up at this training budget.

For a fix: (1) a context that can compare transitions within the window (the slope of d on
v, or pooled second-order features, attention, a recurrent encoder) can resolve the sign
whenever the speed varies; (2) a memory of the whole episode keeps the acceleration from
rest, where v < T and T = v + d is right, instead of a 25-step window that forgets it; (3)
exploration at deployment only helps if it is a deliberate speed probe of a few tenths of a
m/s, not SAC's sampled noise; (4) training data with more overshoot does not teach the sign
to this encoder (seed 2 had 53 %). R^2 of the decoded target is not evidence of adaptation
on this family: seed 3 reaches 0.95 by running below every target.
"""


def main(argv=None) -> int:
    """Run (or re-render) the measure and write the results."""
    p = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    p.add_argument('--runs', nargs='+', default=[f'/work/runs/cv1-zeus-id-s{s}'
                                                 for s in (1, 2, 3)])
    p.add_argument('--episodes', type=int, default=2)
    p.add_argument('--max-steps', type=int, default=1000)
    p.add_argument('--name', default=NAME,
                   help='stem of the .md/.csv written to research/results; the conclusion '
                        "below is the default runs' (zeus-id), other names get none")
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    all_data = {}
    for run in args.runs:
        start = time.time()
        all_data[run] = measure(run, args.episodes, args.max_steps)
        print(f'{run}: {time.time() - start:.0f} s', flush=True)
    lines, csv_rows = render(all_data, args.runs, args.name)
    if args.name == NAME:
        lines += ['## Conclusion', '', CONCLUSION.strip(), '']
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / f'{args.name}.md').write_text('\n'.join(lines) + '\n')
    with open(RESULTS / f'{args.name}.csv', 'w', newline='') as f:
        writer = csv.DictWriter(f, fieldnames=list(csv_rows[0]))
        writer.writeheader()
        writer.writerows(csv_rows)
    print('\n'.join(lines))
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
