"""Per-step inference cost of the controllers' two backends, torch and onnx, side by side.

    python research/benchmarks/bench_inference.py --weights weights/walker-walk-v0-zeus \
        [more weights] [--steps 500] [--rounds 7] \
        [--json research/benchmarks/results_inference.json]

What one control step costs each controller node in inference, as the nodes
call it (batch 1, one thread): the context node's latent and estimates
(`context` + `decode_values`), the policy node's phi(s) and actor
(`features` + `act_on_features`). The inputs are the windows and
observations of a real episode of the weights' own policy (`--steps` steps,
recorded with `zeus_ros.learning_tools.export_onnx.record_inputs`). The backends take turns
round by round, so the machine's other load falls on both alike; reported per
part: the median over rounds of the wall-clock microseconds per step, the CPU
microseconds per step, the ratio onnx / torch, and the largest |onnx - torch|
of the outputs over the episode. The onnx graphs are exported into a
temporary directory first. No ROS, no DDS: the middleware's share is
bench_loop.py's.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
import json
from pathlib import Path
import sys
import tempfile
import time

import numpy as np

from zeus_ros.deploy.inference import DeployedModel, InferenceModel
from zeus_ros.deploy.onnx_export import export_onnx
from zeus_ros.deploy.onnx_model import OnnxInferenceModel
from zeus_ros.learning_tools.export_onnx import largest_differences, record_inputs, RecordedInputs

PARTS = ('context_node', 'policy_node')


@dataclass
class Timing:
    """Wall and CPU microseconds per step of one part, one round."""

    wall_us: float
    cpu_us: float


def run_part(model: DeployedModel, inputs: RecordedInputs, latents: list, part: str) -> Timing:
    """Time one pass of `part` over every recorded step."""
    params = inputs.true_params if model.needs_true_param else [None] * len(latents)
    wall, cpu = time.perf_counter(), time.process_time()
    if part == 'context_node':
        for rows, mask, param in zip(inputs.rows, inputs.masks, params, strict=True):
            model.decode_values(model.context(rows, mask, param))
    else:
        for obs, latent in zip(inputs.observations, latents, strict=True):
            model.act_on_features(model.features(obs), latent)
    n = len(latents)
    return Timing(1e6 * (time.perf_counter() - wall) / n, 1e6 * (time.process_time() - cpu) / n)


def measure(models: dict[str, DeployedModel], inputs: RecordedInputs, rounds: int) -> dict:
    """Median wall and CPU us per step of each part and backend, the backends in turns."""
    latents = {name: [m.context(r, k, p if m.needs_true_param else None) for r, k, p in
                      zip(inputs.rows, inputs.masks, inputs.true_params, strict=True)]
               for name, m in models.items()}
    timings = {(name, part): [] for name in models for part in PARTS}
    for name, model in models.items():   # warm-up: first calls allocate and load lazily
        for part in PARTS:
            run_part(model, inputs, latents[name], part)
    for _ in range(rounds):
        for part in PARTS:
            for name, model in models.items():
                timings[name, part].append(run_part(model, inputs, latents[name], part))
    return {f'{name}_{part}_{kind}': round(float(np.median([getattr(t, kind) for t in ts])), 1)
            for (name, part), ts in timings.items() for kind in ('wall_us', 'cpu_us')}


def bench_weights(weights: Path, steps: int, rounds: int) -> dict:
    """Return the figures of one checkpoint: both backends on one recorded episode."""
    torch_model = InferenceModel.load(weights)
    with tempfile.TemporaryDirectory() as tmp:
        onnx_model = OnnxInferenceModel.load(export_onnx(weights, Path(tmp) / 'onnx'))
        inputs = record_inputs(torch_model, steps)
        figures = measure({'torch': torch_model, 'onnx': onnx_model}, inputs, rounds)
        worst = largest_differences(torch_model, onnx_model, inputs)
    for part in PARTS:
        figures[f'ratio_{part}'] = round(figures[f'onnx_{part}_wall_us']
                                         / figures[f'torch_{part}_wall_us'], 2)
    return {'weights': str(weights), 'method': torch_model.method_name,
            'steps': len(inputs.rows), 'rounds': rounds,
            'largest_difference': max(worst.values()), **figures}


def table(results: list[dict]) -> str:
    """Return one line per checkpoint and backend, wall (CPU) us per step."""
    lines = ['weights                          backend  context node us  policy node us  '
             'step us']
    for r in results:
        for backend in ('torch', 'onnx'):
            parts = [r[f'{backend}_{p}_wall_us'] for p in PARTS]
            cpus = [r[f'{backend}_{p}_cpu_us'] for p in PARTS]
            lines.append(f'{Path(r["weights"]).name:32s} {backend:7s}  '
                         f'{parts[0]:6.1f} ({cpus[0]:6.1f})  {parts[1]:6.1f} ({cpus[1]:6.1f})  '
                         f'{sum(parts):7.1f}')
        lines.append(f'{"":32s} onnx/torch {r["ratio_context_node"]:.2f} and '
                     f'{r["ratio_policy_node"]:.2f}; largest |onnx - torch| '
                     f'{r["largest_difference"]:.1e}')
    return '\n'.join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--weights', type=Path, nargs='+', required=True)
    parser.add_argument('--steps', type=int, default=500, help='steps of the recorded episode')
    parser.add_argument('--rounds', type=int, default=7, help='passes of each backend')
    parser.add_argument('--json', type=Path, help='write the figures here')
    args = parser.parse_args(argv)
    results = [bench_weights(w, args.steps, args.rounds) for w in args.weights]
    print(table(results))
    if args.json:
        args.json.write_text(json.dumps(results, indent=2) + '\n')
    return 0


if __name__ == '__main__':
    sys.exit(main())
