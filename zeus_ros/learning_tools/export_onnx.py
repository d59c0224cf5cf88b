"""Export a checkpoint's deployed networks as ONNX (context, phi, actor, decoder).

    export_onnx --weights weights/walker-walk-v0-zeus [--out DIR] [--check-steps 200]
    python -m zeus_ros.learning_tools.export_onnx --weights ...   (the same without a ROS install)

Writes DIR (default <checkpoint>/onnx): one .onnx file per graph, onnx.json
naming each graph's inputs and outputs (dtype, shape) with the checkpoint's
metadata, and a copy of metadata.json (see zeus_ros.deploy.onnx_export). The
controller nodes run these files with `-p backend:=onnx`.

Then checks the export: records the windows and observations of a short
episode of the weights' own policy in the real simulation (the family's
default task, seed 0), runs both backends on every one, and prints the largest
difference of latent, features, action and estimates; exit code 1 if one
exceeds --tolerance (default 1e-5). --check-steps 0 skips the check.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
import sys

import numpy as np

from zeus_ros.core.window import ContextWindow
from zeus_ros.deploy.checkpoint import CheckpointError
from zeus_ros.deploy.inference import DeployedModel, InferenceModel
from zeus_ros.deploy.onnx_export import export_onnx, MANIFEST
from zeus_ros.deploy.onnx_model import OnnxInferenceModel
from zeus_ros.learning_tools.evaluate import run_episode


@dataclass(frozen=True)
class RecordedInputs:
    """What a deployed model was given at each step of a real episode."""

    rows: np.ndarray          # [T, k, row_dim] float32: the window before each step
    masks: np.ndarray         # [T, k] bool
    observations: np.ndarray  # [T, obs_dim]
    true_params: np.ndarray   # [T, P]: the sim's values (read by privileged methods only)


def record_inputs(model: DeployedModel, steps: int, seed: int = 0) -> RecordedInputs:
    """Run `model` for up to `steps` steps of its family's default task; keep its inputs.

    The windows are rebuilt from the episode's transitions exactly as
    `run_episode` fills its window (the episode never clears it mid-way).
    """
    record = run_episode(model, model.family, None, seed, max_steps=steps)
    window = ContextWindow(model.k, model.obs_dim, model.action_dim)
    rows, masks = [], []
    for t in range(len(record.actions)):
        if t > 0:
            window.push(record.observations[t - 1], record.actions[t - 1],
                        record.rewards[t - 1], record.observations[t])
        r, m = window.arrays()
        rows.append(r.copy())
        masks.append(m.copy())
    params = np.asarray(record.param_values, dtype=np.float64).reshape(len(rows), -1)
    return RecordedInputs(np.asarray(rows, np.float32), np.asarray(masks, bool),
                          np.asarray(record.observations), params)


def largest_differences(a: DeployedModel, b: DeployedModel,
                        inputs: RecordedInputs) -> dict[str, float]:
    """Largest |a - b| of each output over the recorded inputs (both fed a's latent to act)."""
    worst = dict.fromkeys(('latent', 'features', 'action', 'estimates'), 0.0)
    for rows, mask, obs, param in zip(inputs.rows, inputs.masks, inputs.observations,
                                      inputs.true_params, strict=True):
        param = param if a.needs_true_param else None
        latent = a.context(rows, mask, param)
        pairs = {'latent': (latent, b.context(rows, mask, param)),
                 'features': (a.features(obs), b.features(obs)),
                 'action': (a.act(obs, latent), b.act(obs, latent)),
                 'estimates': (np.nan_to_num(a.decode_values(latent)),
                               np.nan_to_num(b.decode_values(latent)))}
        for name, (x, y) in pairs.items():
            worst[name] = max(worst[name], float(np.max(np.abs(x - y), initial=0.0)))
    return worst


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--weights', required=True,
                        help='checkpoint directory (or a run directory holding checkpoint/)')
    parser.add_argument('--out', help='export directory (default: <checkpoint>/onnx)')
    parser.add_argument('--check-steps', type=int, default=200,
                        help='steps of the episode the check records (0: no check)')
    parser.add_argument('--tolerance', type=float, default=1e-5,
                        help='largest |onnx - torch| the check accepts')
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    try:
        out = export_onnx(args.weights, args.out)
        onnx_model = OnnxInferenceModel.load(out)
    except CheckpointError as error:
        print(f'export_onnx: {error}', file=sys.stderr)
        return 1
    print(f'{out}: {", ".join(sorted(onnx_model.sessions))} ({onnx_model.method_name}, '
          f'{onnx_model.family}); described in {out / MANIFEST}')
    if args.check_steps <= 0:
        return 0
    torch_model = InferenceModel.load(args.weights)
    inputs = record_inputs(torch_model, args.check_steps)
    worst = largest_differences(torch_model, onnx_model, inputs)
    print(f'largest |onnx - torch| over {len(inputs.rows)} recorded steps: '
          + ', '.join(f'{name} {value:.1e}' for name, value in worst.items()))
    if max(worst.values()) > args.tolerance:
        print(f'export_onnx: a difference exceeds the tolerance {args.tolerance:g}',
              file=sys.stderr)
        return 1
    return 0


if __name__ == '__main__':
    sys.exit(main())
