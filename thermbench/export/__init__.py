"""Export for the embedded compensator: compact model files, the C runtime's Python side.

* :mod:`.fileformat` - the ``.tbm`` binary format (header, float32 payload, CRC-32);
* :mod:`.encoding` - fitted models of every family and the condition classifier -> payloads;
* :mod:`.reduce` - reduced-set LSSVM;
* :mod:`.bundle` - an export directory written (files, manifest.json; the ONNX file and the parity check
  through the modules below);
  :mod:`.directory` reads one back, :mod:`.samples` (a run as the runtime is fed it), :mod:`.onnxfile`,
  :mod:`.parity` (the C runtime against Python), :mod:`.budget` (the targets and whether an export fits);
* :mod:`.runtime` - build and drive the C runtime in ``embedded/``;
* :mod:`.job` - the ``thermbench export`` Hydra job; :mod:`.replay` - ``thermbench replay``.
"""

from .bundle import ExportOptions, export_model
from .directory import read_manifest, replay_dir
from .encoding import ExportError, encode, encode_classifier, encode_mlr_curve
from .fileformat import Kind, ModelFileError, pack, unpack
from .runtime import RuntimeFailed, RuntimeUnavailable

__all__ = [
    "encode_mlr_curve",
    "ExportError", "ExportOptions", "Kind", "ModelFileError", "RuntimeFailed", "RuntimeUnavailable", "encode",
    "encode_classifier", "export_model", "pack", "read_manifest", "replay_dir", "unpack",
]  # fmt: skip
