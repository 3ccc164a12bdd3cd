"""``thermbench`` command line: a thin layer over importable functions.

    thermbench simulate [hydra overrides...]   write a dataset (or suite=benchmark: all standard ones)
    thermbench validate DATA_DIR               check a dataset against the contract and summarise it
    thermbench import MAPPING.yaml --out DIR [--format csv|parquet] [--force]
                                               a lab's own files (CSV, Excel, Parquet) -> a dataset (docs/import.md)
    thermbench iso230 DATA_DIR --out DIR [--force]
                                               ISO 230-2 / 230-3 figures of a thermal test (docs/iso230.md)
    thermbench classify --stroke S --start A --end B --feed F
                                               seed 002 §2.4 condition classifier: the chosen condition
    thermbench diagnose DATA_DIR --out OUT_DIR [--base EFFECT,...] [--max-effects K] [overrides...]
                                               discrepancy workflow: name the effect the physics model misses
    thermbench replay MODEL_DIR DATA_DIR --run ID [--probes FILE] [--out OUT_DIR] [--force]
                                               an exported model in the C runtime over a run's log: before/after
    thermbench precompensate PROGRAM.nc --model MODEL.joblib --out OUT.nc [--verify] [...]
    thermbench precompensate PROGRAM.nc --models axes.yaml --out OUT.nc [--verify] [...]
                                               seed 003: rewrite a part program against the predicted error
    thermbench compensator MODEL_DIR --endpoint opc.tcp://HOST:PORT --nodes nodes.yaml [overrides...]
                                               OPC UA compensator: the exported model against a live machine
    thermbench sim-cnc [--endpoint URL] [overrides...]
                                               a simulated CNC axis behind an OPC UA server (closed loop)
    thermbench station STATION.yaml [overrides...]
                                               one compensator for several axes and spindle channels
    thermbench certs OUT_DIR                   self-signed certificates for Basic256Sha256 sign-and-encrypt
    thermbench linuxcnc component|plant|sim [MODEL_DIR] [overrides...]
                                               LinuxCNC: the HAL component, a simulated plant, a closed loop
    thermbench train|evaluate|benchmark|export [hydra overrides...] [-m]
                                               Hydra jobs (thermbench.app): conf/<job>.yaml

The package: :mod:`.parser` (the commands and their options) → :mod:`.entry` (:func:`main`: the exit
code, a user's mistake in one line) → :mod:`.commands` (each command, a thin call into the function
that does the work).
"""

import thermbench

from .entry import main

__all__ = ["main"]

__getattr__ = thermbench.moved_names(__name__)  # the commands were in thermbench/cli.py (MOVED_NAMES)
