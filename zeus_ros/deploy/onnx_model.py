"""The `onnx` backend: a checkpoint's deployed networks run in ONNX Runtime.

    model = OnnxInferenceModel.load(path)    # the interface of InferenceModel

`path` is a checkpoint directory (or a run directory holding `checkpoint/`)
or an export directory written by `zeus_ros.learning_tools.export_onnx` (it holds onnx.json
and a copy of metadata.json). For a checkpoint the graphs come from its
``onnx/`` export when that export is of these weights (onnx.json's
``source.model_sha256`` is the checkpoint's model.safetensors SHA-256);
otherwise they are exported on the fly into a cache directory,
``$ZEUS_ONNX_CACHE`` (default ``$XDG_CACHE_HOME/zeus_ros/onnx``, i.e.
``~/.cache/zeus_ros/onnx``) under the weights' SHA-256, where the next load
finds them. Every graph's SHA-256 and size are checked against onnx.json
before it is loaded; anything wrong raises CheckpointError.

Each session runs one intra-op thread, sequentially, as the torch backend.
The outputs agree with torch's within 1e-5, not bit for bit (other kernels,
another order of the sums): test/test_onnx.py.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import onnxruntime as ort

from zeus_ros.deploy.checkpoint import (CheckpointError, load_metadata, MODEL_FILE, resolve_dir,
                                        sha256_file)
from zeus_ros.deploy.inference import DeployedModel
from zeus_ros.deploy.metadata import CheckpointMetadata
from zeus_ros.deploy.onnx_export import (DEFAULT_SUBDIR, export_onnx, MANIFEST,
                                         MANIFEST_FORMAT)


def cache_root() -> Path:
    """Where exports made on the fly go: $ZEUS_ONNX_CACHE, else the user's cache directory."""
    if os.environ.get('ZEUS_ONNX_CACHE'):
        return Path(os.environ['ZEUS_ONNX_CACHE'])
    base = os.environ.get('XDG_CACHE_HOME') or Path.home() / '.cache'
    return Path(base) / 'zeus_ros' / 'onnx'


def read_manifest(export_dir: Path) -> dict | None:
    """Return onnx.json of an export directory, or None if there is none of this format."""
    try:
        manifest = json.loads((export_dir / MANIFEST).read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        return None
    ok = isinstance(manifest, dict) and manifest.get('format_version') == MANIFEST_FORMAT
    return manifest if ok else None


def _fresh(export_dir: Path, model_sha256: str) -> dict | None:
    """Return the manifest of an export of exactly these weights in `export_dir`, else None."""
    manifest = read_manifest(export_dir)
    if manifest is None or manifest.get('source', {}).get('model_sha256') != model_sha256:
        return None
    return manifest


def locate_export(checkpoint: Path, meta: CheckpointMetadata) -> tuple[Path, dict]:
    """(export directory, manifest) for a checkpoint: its own onnx/, the cache, or new."""
    if (checkpoint / MANIFEST).exists():   # an export directory itself
        manifest = read_manifest(checkpoint)
        if manifest is None:
            raise CheckpointError(f'{checkpoint / MANIFEST} is unreadable or of another '
                                  f'format (this code reads format {MANIFEST_FORMAT})')
        return checkpoint, manifest
    if MODEL_FILE not in meta.files:
        raise CheckpointError(f'{checkpoint}: metadata lists no {MODEL_FILE}')
    sha = meta.files[MODEL_FILE].sha256
    for candidate in (checkpoint / DEFAULT_SUBDIR, cache_root() / sha[:32]):
        manifest = _fresh(candidate, sha)
        if manifest is not None:
            return candidate, manifest
    try:
        out = export_onnx(checkpoint, cache_root() / sha[:32], replace=False)
    except OSError as error:
        raise CheckpointError(f'{checkpoint} has no ONNX export and none can be written to '
                              f'the cache ({error}): set ZEUS_ONNX_CACHE or run export_onnx '
                              '--weights first') from None
    manifest = _fresh(out, sha)
    if manifest is None:
        raise CheckpointError(f'the ONNX export in {out} is not of {checkpoint}')
    return out, manifest


def _session(export_dir: Path, entry: dict) -> ort.InferenceSession:
    """Open an ONNX Runtime session of one graph, after checking the file against onnx.json."""
    path = export_dir / entry['file']
    if not path.exists():
        raise CheckpointError(f'{path} is missing')
    if path.stat().st_size != entry['bytes'] or sha256_file(path) != entry['sha256']:
        raise CheckpointError(f'{path} does not match its size and SHA-256 in {MANIFEST} '
                              '(corrupt or replaced)')
    options = ort.SessionOptions()
    options.intra_op_num_threads = 1
    options.inter_op_num_threads = 1
    options.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    return ort.InferenceSession(str(path), options, providers=['CPUExecutionProvider'])


class OnnxInferenceModel(DeployedModel):
    """phi, the context, actor and decoder of a checkpoint, run in ONNX Runtime."""

    def __init__(self, meta: CheckpointMetadata, manifest: dict, export_dir: Path):
        super().__init__(meta, int(manifest['context_dim']),
                         bool(manifest['needs_true_param']))
        self.export_dir = export_dir
        self.backend_note = f'onnx, graphs from {export_dir}'
        self.sessions = {name: _session(export_dir, entry)
                         for name, entry in manifest['graphs'].items()}
        self.inputs = {name: [i.name for i in s.get_inputs()]
                       for name, s in self.sessions.items()}

    @classmethod
    def load(cls, path: str | Path, expected_family: str | None = None,
             obs_dim: int | None = None, action_dim: int | None = None) -> 'OnnxInferenceModel':
        """Load the ONNX export of a checkpoint (made on the fly if it has none)."""
        meta = load_metadata(path, expected_family, obs_dim, action_dim)
        export_dir, manifest = locate_export(resolve_dir(path), meta)
        return cls(meta, manifest, export_dir)

    def _run(self, graph: str, **values) -> np.ndarray:
        return self.sessions[graph].run(None, {n: values[n] for n in self.inputs[graph]})[0]

    def _context(self, rows: np.ndarray, mask: np.ndarray,
                 param: np.ndarray | None) -> np.ndarray:
        if 'context' not in self.sessions:
            return np.zeros((rows.shape[0], 0), dtype=np.float32)   # sac: no context
        if param is None and 'true_param' in self.inputs['context']:
            raise ValueError(f'the {self.method_name} method needs the true parameter')
        return self._run('context', rows=rows, mask=mask, true_param=param)

    def _features(self, obs: np.ndarray) -> np.ndarray:
        return self._run('phi', obs=obs)

    def _act(self, features: np.ndarray, latent: np.ndarray) -> np.ndarray:
        return self._run('actor', features=features, latent=latent)

    def _decode(self, latent: np.ndarray) -> np.ndarray | None:
        if 'decoder' not in self.sessions:
            return None
        return self._run('decoder', latent=latent)
