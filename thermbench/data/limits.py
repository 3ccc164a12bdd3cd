"""What a dataset may hold: size caps, the run-id rule and the plausible range of every
quantity (docs/dataset-format.md, "Limits"). One place, used by the loader
(:mod:`thermbench.data.io`) and the metadata schema (:mod:`thermbench.data.schema`)."""

from __future__ import annotations

import math
import os
import re
from dataclasses import dataclass

from .errors import DatasetError

MiB = 1024 * 1024

# ------------------------------------------------------------------ sizes ---
METADATA_MAX_BYTES = 1 * MiB  # metadata.yaml; a real one is a few kB

#: the environment variable that sets the table cap (MiB) for every command, overriding the default
TABLE_CAP_ENV = "THERMBENCH_MAX_TABLE_MIB"
#: the share of the machine's memory one table may take by default (never below 256 MiB)
TABLE_MEMORY_FRACTION = 0.25


def machine_memory_bytes() -> int:
    """The machine's physical memory (8 GiB where the system does not say)."""
    try:
        return int(os.sysconf("SC_PAGE_SIZE")) * int(os.sysconf("SC_PHYS_PAGES"))
    except (AttributeError, ValueError, OSError):
        return 8 * 1024 * MiB


def table_cap_bytes(mib: float | None = None) -> int:
    """The most bytes one table (a file to import, a dataset's process or errors table) may hold:
    ``mib`` when given, else ``$THERMBENCH_MAX_TABLE_MIB`` (for one command:
    ``THERMBENCH_MAX_TABLE_MIB=2048 thermbench import ...``), else a quarter of the machine's
    memory and at least 256 MiB. A guard against absurd inputs that
    scales with the machine (docs/dataset-format.md, "Limits")."""
    if mib is None:
        env = os.environ.get(TABLE_CAP_ENV, "").strip()
        if env:
            try:
                mib = float(env)
            except ValueError:
                mib = None
            if mib is None or not (mib > 0 and math.isfinite(mib)):
                raise DatasetError(f"${TABLE_CAP_ENV}={env!r}: expected a size in MiB, > 0")
    if mib is not None:
        return int(mib * MiB)
    return max(256 * MiB, int(machine_memory_bytes() * TABLE_MEMORY_FRACTION))


TABLE_MAX_BYTES = table_cap_bytes()  # process/errors, .csv or .parquet, on disk
# cells (rows x columns) of one table: bounds the memory a table takes once read,
# whatever its encoding (a parquet file of constants decodes to 8 bytes per cell
# from almost nothing; a CSV of "0,0,0" to 4 times its size): as many float64 cells as the
# table cap holds (at least 32 M: about 3 M rows of a process log with 10 columns, 35 days at 1 Hz)
TABLE_MAX_CELLS = max(32_000_000, TABLE_MAX_BYTES // 8)
# a Parquet table's bytes once decompressed (its footer's count, checked before reading)
# and its text columns' bytes once decoded (checked before expanding them)
TABLE_MAX_DECODED_BYTES = TABLE_MAX_BYTES
CSV_HEADER_MAX_BYTES = 64 * 1024  # the header line of a CSV table
YAML_MAX_DEPTH = 32  # nesting of mappings/sequences in metadata.yaml (a dataset needs 4)
# values (scalars, mappings, lists) in metadata.yaml: a run takes about 15, so 100 000 is
# some 6 000 runs; parsing them takes about a second (1 MiB of "[1,1,1,...]" would take 5)
YAML_MAX_NODES = 100_000

# ---------------------------------------------------------------- run ids ---
RUN_ID_MAX_LEN = 64
RUN_ID_PATTERN = r"[A-Za-z0-9](?:[A-Za-z0-9_.-]{0,62}[A-Za-z0-9_-])?"
RUN_ID_RE = re.compile(RUN_ID_PATTERN)
RUN_ID_RULE = (
    "1-64 characters from A-Z a-z 0-9 _ . -, starting with a letter or digit and not ending with '.'"
    " (a run id names MLflow metrics and files)"
)
# names Windows reserves for devices, also with an extension ("con.csv")
WINDOWS_DEVICE_NAMES = frozenset(
    ["CON", "PRN", "AUX", "NUL"] + [f"COM{i}" for i in range(1, 10)] + [f"LPT{i}" for i in range(1, 10)]
)


def run_id_problem(run_id: object) -> str | None:
    """Why ``run_id`` breaks the run-id rule, or None when it obeys it."""
    if not isinstance(run_id, str):
        return (
            f"is not text but {type(run_id).__name__} {run_id!r}: quote it in YAML (\"1\":, \"on\":); "
            "bare numbers, dates and yes/no/on/off/true/false are not text"
        )
    if RUN_ID_RE.fullmatch(run_id) is not None:
        if run_id.split(".")[0].upper() in WINDOWS_DEVICE_NAMES:
            return "is a name Windows reserves for a device (CON, NUL, COM1, ...): it cannot name a file"
        return None
    if not run_id:
        return "is empty"
    if run_id != run_id.strip():
        return "has leading or trailing whitespace"
    if len(run_id) > RUN_ID_MAX_LEN:
        return f"is {len(run_id)} characters long (at most {RUN_ID_MAX_LEN})"
    bad = sorted({c for c in run_id if not (c.isascii() and (c.isalnum() or c in "_.-"))})
    if bad:
        shown = " ".join(repr(c) for c in bad[:5])
        return f"contains {shown}, not allowed"
    if not run_id[0].isalnum():
        return f"starts with {run_id[0]!r}: it must start with a letter or digit"
    return "ends with '.'"  # the only case left


def natural_key(name: str) -> tuple:
    """The key that sorts names as a person reads them: the runs of digits as numbers, the rest as text
    without regard to case (``run2`` before ``run10``, ``Sheet 9`` before ``sheet 10``; ISO dates in date
    order). Names equal under it are ordered by the name itself."""
    parts = re.split(r"(\d+)", str(name))
    return tuple((0, int(p), "") if p.isdecimal() else (1, 0, p.casefold()) for p in parts if p), str(name)


def run_id_key(run_id: str) -> str:
    """Run ids equal under this key name the same run for a person, a case-insensitive
    file system (Windows, macOS) or a spreadsheet: they must not both occur."""
    return run_id.strip().casefold()


# ------------------------------------------------------------ quantities ---
def _g(v: float) -> str:
    return f"{v:.6g}"


@dataclass(frozen=True)
class Quantity:
    """The plausible range of one quantity, and the unit mistake a value outside it suggests."""

    unit: str
    lo: float
    hi: float
    lo_inclusive: bool = True
    # (lo, hi, unit, factor): an out-of-range value in [lo, hi] looks like it is in `unit`;
    # the value meant is value * factor (factor None: a hint without a conversion)
    hint: tuple[float, float, str, float | None] | None = None

    def range_text(self) -> str:
        return f"{'>=' if self.lo_inclusive else '>'} {_g(self.lo)} and <= {_g(self.hi)} {self.unit}"

    def problem(self, value: float) -> str | None:
        """Why ``value`` is not plausible (with the unit), or None."""
        if not math.isfinite(value):
            return f"must be a finite number of {self.unit}, got {value!r}"
        ok_lo = value >= self.lo if self.lo_inclusive else value > self.lo
        if ok_lo and value <= self.hi:
            return None
        msg = f"must be {self.range_text()}, got {_g(value)}"
        if self.hint is not None:
            h_lo, h_hi, h_unit, factor = self.hint
            if factor is None and h_lo <= value <= h_hi:
                msg += f"; {_g(value)} looks like {h_unit}"
            elif factor is not None and h_lo <= abs(value) <= h_hi and self.problem(value * factor) is None:
                msg += f"; {_g(value)} looks like {h_unit}: write {_g(value * factor)}"
        return msg


# metadata.yaml
LENGTH_M = Quantity("m", 0.0, 20.0, lo_inclusive=False, hint=(20.0, 20000.0, "mm", 1e-3))
DIAMETER_M = Quantity("m", 0.0, 1.0, lo_inclusive=False, hint=(1.0, 1000.0, "mm", 1e-3))
BEARING_LENGTH_M = Quantity("m", 0.0, 20.0, hint=(20.0, 20000.0, "mm", 1e-3))
ALPHA_PER_K = Quantity("1/K", 1e-7, 1e-4, hint=(0.1, 100.0, "µm/(m·K) (1e-6/K)", 1e-6))
DENSITY_KG_M3 = Quantity("kg/m³", 500.0, 25_000.0, hint=(0.5, 25.0, "g/cm³", 1e3))
HEAT_CAPACITY_J_KGK = Quantity("J/(kg·K)", 100.0, 5_000.0, hint=(0.1, 5.0, "kJ/(kg·K) or J/(g·K)", 1e3))
STROKE_MM = Quantity("mm", 0.0, 200_000.0, hint=(200_000.0, 2e11, "µm", 1e-3))

# metadata.yaml and tables
POSITION_MM = Quantity("mm", -100_000.0, 100_000.0, hint=(100_000.0, 1e11, "µm", 1e-3))  # 100 m
FEED_MM_MIN = Quantity("mm/min", 0.0, 200_000.0, hint=(200_000.0, 2e11, "µm/min", 1e-3))  # 200 m/min

# tables
# -130 °C, not -50: a DS18B20 reads -127 when disconnected, a dropout the limit filter
# removes like its 85 °C power-on reading; nothing a machine tool reaches lies below
TEMPERATURE_C = Quantity("°C", -130.0, 200.0, hint=(250.0, 400.0, "kelvin (°C = K - 273.15)", None))
ERROR_UM = Quantity("µm", -5_000.0, 5_000.0, hint=(5_000.0, 5e9, "nm", 1e-3))  # 5 mm: no thermal or pitch error

# contract v2 (docs/dataset-format.md, "Version 2")
SPINDLE_RPM = Quantity("1/min", 0.0, 500_000.0)  # the fastest spindles turn at some 200 000 rpm
LOAD_N = Quantity("N", -10_000_000.0, 10_000_000.0, hint=(1e7, 1e10, "mN", 1e-3))
MAX_GAP_S = Quantity("s", 0.0, 86_400.0, lo_inclusive=False, hint=(86_400.0, 8.64e7, "ms", 1e-3))
TILT_URAD = Quantity("µrad", -50_000.0, 50_000.0, hint=(50_000.0, 5e10, "nrad", 1e-3))
TIME_S = Quantity("s", -1e9, 1e9)  # 30 years either side of a run's clock zero
