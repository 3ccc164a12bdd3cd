"""The standard benchmark datasets, built deterministically from seeds and cached.

Each is ``thermbench simulate`` with ``truth=benchmark`` (a finer grid and
several effects beyond the seed 000 core: docs/benchmark-truth.md) and the
overrides listed in ``conf/benchmark_datasets.yaml``. A dataset is rebuilt
only when the hash of its resolved config (and of the simulator revision)
differs from the one recorded in its ``metadata.yaml``.
"""

from __future__ import annotations

import fcntl
import hashlib
import json
import os
from contextlib import contextmanager
from pathlib import Path
from typing import Sequence

import yaml
from omegaconf import OmegaConf

from .. import __version__
from ..config import ConfigError, config_dir, load_config
from ..outputs import check_output_dir
from ..data.io import Dataset, load_dataset, save_dataset
from ..sim.scenario import simulate_dataset

SIM_REVISION = 1  # bump when the simulator's numbers change for the same config


# measured datasets shipped in the package: name -> import mapping (docs/import.md)
REAL = {"fl_thermal": "realdata/fl_thermal/mapping.yaml"}


def names() -> list[str]:
    """The simulated benchmark datasets (``thermbench simulate suite=benchmark``)."""
    return list(_registry())


def real_names() -> list[str]:
    """The measured datasets shipped with thermbench (imported on first use, no network)."""
    return list(REAL)


def of_key(key: str) -> str | None:
    """The benchmark dataset a model key names: ``<dataset>__<family>__<approach>`` (benchmark
    model files), ``<dataset>-...`` (logged model names) or ``thermbench-<dataset>[-...]``
    (registered names); None when it names none."""
    for name in sorted(names() + real_names(), key=len, reverse=True):
        if key.startswith((f"{name}__", f"{name}-", f"thermbench-{name}-")) or key == f"thermbench-{name}":
            return name
    return None


def _registry() -> dict:
    return yaml.safe_load((config_dir() / "benchmark_datasets.yaml").read_text(encoding="utf-8"))


def default_root() -> Path:
    return Path(os.environ.get("THERMBENCH_DATA") or "data/benchmark")  # set but empty: the default


def benchmark_config(name: str, extra_overrides: tuple[str, ...] = ()):
    reg = _registry()
    if name not in reg:
        raise ConfigError(f"config key 'dataset.source.name': unknown benchmark dataset {name!r}; known: {sorted(reg)}")
    ov = ["truth=benchmark", "file_format=parquet", *reg[name]["overrides"], *extra_overrides]
    return load_config("simulate", ov)


def config_hash(cfg) -> str:
    plain = OmegaConf.to_container(cfg, resolve=True)
    for key in ("out_dir", "suite", "benchmark_root", "force"):
        plain.pop(key, None)
    blob = json.dumps({"cfg": plain, "rev": SIM_REVISION, "version": __version__}, sort_keys=True, default=str)
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


def _cached_value(path: Path, key: tuple[str, str]) -> str | None:
    """The text at ``key`` (``("simulation", "config_hash")``) of the ``metadata.yaml`` of a
    cached dataset at ``path``, read by the strict loader (no aliases, duplicate keys or
    oversize files); None when the file is missing or unreadable (the dataset is then rebuilt)."""
    from ..data.errors import DatasetError
    from ..data.files import read_capped
    from ..data.limits import METADATA_MAX_BYTES
    from ..data.safe_yaml import load_yaml

    meta = path / "metadata.yaml"
    if not os.path.lexists(meta):
        return None
    try:
        text = read_capped(meta, METADATA_MAX_BYTES, "metadata.yaml").decode("utf-8-sig")
        data, _ = load_yaml(text)
    except (DatasetError, UnicodeDecodeError):  # YAMLInputError is a DatasetError
        return None
    block = data.get(key[0]) if isinstance(data, dict) else None
    value = block.get(key[1]) if isinstance(block, dict) else None
    # written by dump_yaml, a hash reads back as text; one written before as a number: rebuilt
    return value if isinstance(value, str) else None


def _cached_hash(path: Path) -> str | None:
    return _cached_value(path, ("simulation", "config_hash"))


@contextmanager
def _locked(path: Path):
    """An exclusive lock on ``path`` (a sibling lock file), so parallel jobs of a sweep
    never build the same dataset at the same time."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path.parent / f".{path.name}.lock", "a") as fh:  # "a": an existing file is never truncated
        fcntl.flock(fh, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)


def _build_cached(cfg, path: Path, force: bool, **tags) -> tuple[Path, dict | None]:
    """Simulate ``cfg`` into ``path`` unless the dataset there has the same config hash."""
    h = config_hash(cfg)
    if not force and _cached_hash(path) == h:
        return path, None
    check_output_dir(path, "dataset", force_option="")  # before the lock file and the simulation
    with _locked(path):
        if not force and _cached_hash(path) == h:  # built by another job while we waited
            return path, None
        return _build(cfg, path, h, tags)


def _build(cfg, path: Path, h: str, tags: dict) -> tuple[Path, dict]:
    ds, summary = simulate_dataset(cfg)
    sim = dict(ds.metadata.model_extra.get("simulation", {}))
    sim["config_hash"] = h
    sim.update(tags)
    ds.metadata.simulation = sim
    save_dataset(ds, path, file_format=str(cfg.file_format), force_option="")
    return path, summary


def build(name: str, root: str | Path | None = None, force: bool = False) -> tuple[Path, dict | None]:
    """Build benchmark dataset ``name`` under ``root`` unless a matching cache exists.

    Returns the path and the simulation summary (None when taken from the cache).
    """
    return _build_cached(benchmark_config(name), Path(root or default_root()) / name, force, benchmark=name)


def is_built(name: str, root: str | Path | None = None) -> bool:
    """Simulated benchmark dataset ``name`` is under ``root`` as its current config makes it
    (:func:`build` would take it from there, not simulate)."""
    return _cached_hash(Path(root or default_root()) / name) == config_hash(benchmark_config(name))


def load_benchmark(name: str, root: str | Path | None = None) -> Dataset:
    """The validated benchmark dataset ``name`` (built on first use): simulated, or measured
    (:data:`REAL`, imported from the files shipped in the package)."""
    if name in REAL:
        return load_dataset(import_real(name, root))
    path, _ = build(name, root)
    return load_dataset(path)


def import_real(name: str, root: str | Path | None = None) -> Path:
    """Import the shipped measurement ``name`` with its mapping into ``root/name``, unless
    the dataset there was imported from the same mapping and files (their SHA-256)."""
    from ..data.importer import import_dataset

    mapping = Path(__file__).resolve().parents[1] / REAL[name]  # thermbench/realdata/..., shipped in the package
    h = hashlib.sha256()
    for f in sorted(mapping.parent.iterdir()):
        if f.is_file():
            h.update(f.name.encode() + b"\0" + f.read_bytes())
    digest = h.hexdigest()[:16]
    path = Path(root or default_root()) / name
    if _cached_import(path) == digest:
        return path
    check_output_dir(path, "dataset", force_option="")
    with _locked(path):
        if _cached_import(path) != digest:
            import_dataset(mapping, path, extra={"imported": {"mapping": f"thermbench/{REAL[name]}", "sha256": digest}})
    return path


def _cached_import(path: Path) -> str | None:
    return _cached_value(path, ("imported", "sha256"))


def simulated(
    machine: str = "seed001_vmc_x",
    protocol: str = "seed001_states",
    seed: int = 0,
    truth: str = "benchmark",
    sensor_noise_C: float | None = None,
    interferometer_noise_um: float | None = None,
    overrides: Sequence[str] = (),
    root: str | Path | None = None,
) -> Dataset:
    """A dataset simulated from ``conf/`` (machine x protocol x truth, ``seed``), cached by its
    config hash, so a sweep can vary machine, protocol, seed or instrument noise.

    ``sensor_noise_C`` / ``interferometer_noise_um`` set the instrument noise (standard
    deviations); None keeps ``conf/instruments``. ``overrides`` are further ``thermbench
    simulate`` overrides. The dataset lives in ``root/<machine>__<protocol>__<hash>``
    (root default: ``data/simulated`` beside the benchmark root).
    """
    ov = [f"machine={machine}", f"protocol={protocol}", f"truth={truth}", f"seed={int(seed)}", "file_format=parquet"]
    if sensor_noise_C is not None:
        ov.append(f"instruments.sensor.noise_C={float(sensor_noise_C)}")
    if interferometer_noise_um is not None:
        ov.append(f"instruments.interferometer.noise_um={float(interferometer_noise_um)}")
    cfg = load_config("simulate", [*ov, *[str(o) for o in overrides]])
    h = config_hash(cfg)
    base = Path(root) if root is not None else default_root().parent / "simulated"
    path, _ = _build_cached(cfg, base / f"{cfg.machine.name}__{cfg.protocol.name}__{h}", False)
    return load_dataset(path)
