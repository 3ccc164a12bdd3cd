"""``nodes.yaml``: which OPC UA nodes of the machine the compensator reads and writes.

A machine's controller publishes its axis state and the temperature sensors under its
own node ids; this file maps them to the exported model's inputs (the sensor names of
its ``manifest.json``) and names the nodes the compensation goes to. Example (the
address space of ``thermbench sim-cnc``, which can write this file for a model with
``--write-nodes``)::

    inputs:
      axis_mm: "ns=2;s=X.Position_mm"
      feed_mm_min: "ns=2;s=X.Feed_mm_min"
      load_N: null                      # only for models that read the axial load
      measuring: "ns=2;s=X.Measuring"   # optional: inside a measuring cycle (banks)
      done: "ns=2;s=Machine.ProgramDone"  # optional: the compensator stops when true
      heartbeat: null                   # optional: a value that changes every machine cycle (stale if not)
      temperatures:                     # every sensor the model reads, by manifest name
        T_nut: "ns=2;s=X.T_nut_C"
    outputs:
      value:                            # compensation at the current axis position
        node: "ns=2;s=X.TempComp_um"
        unit: um
      line:                             # the controller's own temperature compensation:
        offset: {node: "ns=2;s=X.SD43900_TEMP_COMP_ABS_VALUE", unit: mm}
        slope:  {node: "ns=2;s=X.SD43910_TEMP_COMP_SLOPE", unit: ratio}
        ref:    {node: "ns=2;s=X.SD43920_TEMP_COMP_REF_POSITION", unit: mm}
      status: "ns=2;s=X.TempComp_Status"  # optional: the flags word of every cycle

The compensator writes to these output nodes and to no other (a write anywhere else is
refused before it reaches the network); an output node may not also be an input.
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, PrivateAttr, ValidationError, field_validator

from ..data.errors import DatasetError
from ..data.files import read_capped
from ..data.limits import METADATA_MAX_BYTES
from ..data.safe_yaml import YAMLInputError, load_yaml

# value of 1 µm in each unit a controller may take a length or a slope in
LENGTH_UNITS = {"um": 1.0, "mm": 1e-3, "0.1um": 10.0}  # Beckhoff P-AXIS-00272/273: 0.1 µm
SLOPE_UNITS = {"um_per_m": 1.0, "ratio": 1e-6}  # Beckhoff P-AXIS-00274: µm/m; SINUMERIK tan(beta)


class NodesError(ValueError):
    """A nodes file that cannot be used (names the file and key)."""


#: the largest nodes or station file read (a real one is a few hundred bytes)
NODES_MAX_BYTES = METADATA_MAX_BYTES


def read_yaml_file(path: Path, what: str, error: type[Exception] = NodesError) -> object:
    """The data of the user's YAML file ``path`` (``what`` names its role in messages), read by
    the strict loader (:func:`thermbench.data.safe_yaml.load_yaml`: no aliases, anchors, merge
    keys or duplicate keys, at most :data:`NODES_MAX_BYTES`); any problem is one ``error``
    line naming the file (and the line)."""
    try:
        data = read_capped(path, NODES_MAX_BYTES, what)
        text = data.decode("utf-8-sig")
        return load_yaml(text)[0]
    except UnicodeDecodeError as exc:
        line = data.count(b"\n", 0, exc.start) + 1
        raise error(f"{path}: line {line}: not UTF-8 text (byte 0x{data[exc.start]:02x}); save the file as UTF-8") from None
    except YAMLInputError as exc:
        raise error(f"{path}: {exc}") from None
    except DatasetError as exc:  # not a regular file, too large: the message starts with the path
        raise error(str(exc)) from None


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid")

    @field_validator("*", mode="before")
    @classmethod
    def _no_blank(cls, v):
        if isinstance(v, str) and not v.strip():
            raise ValueError("an empty node id")
        return v


class LengthNode(_Strict):
    node: str
    unit: Literal["um", "mm", "0.1um"] = "um"


class SlopeNode(_Strict):
    node: str
    unit: Literal["um_per_m", "ratio"] = "ratio"


class LineNodes(_Strict):
    offset: LengthNode  # error-line value at the reference position (SINUMERIK SD43900)
    slope: SlopeNode  # its gradient (SD43910)
    ref: LengthNode  # the reference position (SD43920)


class Inputs(_Strict):
    axis_mm: str
    feed_mm_min: str
    load_N: str | None = None
    measuring: str | None = None
    done: str | None = None
    heartbeat: str | None = None
    probe: str | None = None  # a probe reading: the measured error (µm, the model's sign), taken once per new timestamp
    temperatures: dict[str, str]
    operating: dict[str, str] = {}  # operating inputs of the model by manifest name (a spindle's spindle_rpm)


class Outputs(_Strict):
    value: LengthNode | None = None
    line: LineNodes | None = None
    status: str | None = None


class Nodes(_Strict):
    inputs: Inputs
    outputs: Outputs
    _path: str | None = PrivateAttr(default=None)  # the file it was read from (load_nodes)

    @property
    def path(self) -> str | None:
        """The nodes file these nodes were read from (None when built in code)."""
        return self._path

    def _inputs(self) -> list[tuple[str, str, str]]:
        """(input name, key path in the nodes file as written, node id), in read order; temperatures
        are named ``<sensor>_C`` (key ``inputs.temperatures.<sensor>``)."""
        i = self.inputs
        rows = [("axis_mm", "inputs.axis_mm", i.axis_mm), ("feed_mm_min", "inputs.feed_mm_min", i.feed_mm_min)]
        rows += [(k, f"inputs.{k}", getattr(i, k)) for k in ("load_N", "measuring", "done", "heartbeat", "probe") if getattr(i, k)]
        rows += [(f"{s}_C", f"inputs.temperatures.{s}", n) for s, n in i.temperatures.items()]
        rows += [(o, f"inputs.operating.{o}", n) for o, n in i.operating.items()]
        return rows

    def _outputs(self) -> list[tuple[str, str, str]]:
        """(output name, key path in the nodes file, node id): the only nodes the compensator may write."""
        o, rows = self.outputs, []
        if o.value:
            rows.append(("value", "outputs.value.node", o.value.node))
        if o.line:
            rows += [(k, f"outputs.line.{k}.node", getattr(o.line, k).node) for k in ("offset", "slope", "ref")]
        if o.status:
            rows.append(("status", "outputs.status", o.status))
        return rows

    def input_keys(self) -> dict[str, str]:
        """input name (as in :meth:`input_ids`) -> its key path in the nodes file, as written."""
        return {name: key for name, key, _ in self._inputs()}

    def output_keys(self) -> dict[str, str]:
        """output name (as in :meth:`output_ids`) -> its key path in the nodes file."""
        return {name: key for name, key, _ in self._outputs()}

    def where(self, name: str, output: bool = False) -> str:
        """Where the input (or output) ``name`` is set, for a message: ``<file>: key <key path>``
        (``nodes file: key ...`` when the nodes were not read from a file)."""
        key = (self.output_keys() if output else self.input_keys()).get(name)
        return f"{self._path or 'nodes file'}: key {key}" if key else f"{self._path or 'nodes file'}"

    def input_ids(self) -> dict[str, str]:
        """input name -> node id (temperatures as ``<sensor>_C``), in read order."""
        return {name: nid for name, _, nid in self._inputs()}

    def output_ids(self) -> dict[str, str]:
        """output name -> node id: the only nodes the compensator may write."""
        return {name: nid for name, _, nid in self._outputs()}


def _where(loc: tuple) -> str:
    return ".".join(str(p) for p in loc)


def load_nodes(path: str | Path, sensors: list[str] | None = None, needs_load: bool = False,
               output: str = "value", operating: list[str] | None = None) -> Nodes:  # fmt: skip
    """Read and check ``path`` against the model (its ``sensors``, whether it reads the load)
    and the output form (``value``, ``line`` or ``both``)."""
    path = Path(path)
    if not path.exists():
        raise NodesError(f"{path}: no such nodes file (see thermbench/compensator/nodes.py for its form)")
    raw = read_yaml_file(path, "a nodes file")
    try:
        nodes = Nodes.model_validate(raw if raw is not None else {})
    except ValidationError as exc:
        e = exc.errors()[0]
        raise NodesError(f"{path}: key {_where(e['loc']) or '(top)'}: {e['msg']}") from None
    nodes._path = str(path)
    missing = [s for s in (sensors or []) if s not in nodes.inputs.temperatures]
    if missing:
        raise NodesError(f"{path}: key inputs.temperatures: the model reads sensor(s) {missing}, which have no node; "
                         f"mapped: {sorted(nodes.inputs.temperatures)}")  # fmt: skip
    missing = [o for o in (operating or []) if o not in nodes.inputs.operating]
    if missing:
        raise NodesError(f"{path}: key inputs.operating: the model reads operating input(s) {missing}, which have no node")
    if needs_load and not nodes.inputs.load_N:
        raise NodesError(f"{path}: key inputs.load_N: the model reads the axial load, so it needs a node")
    if output not in ("value", "line", "both"):
        raise NodesError(f"compensator output {output!r}: expected value, line or both")
    if output in ("value", "both") and nodes.outputs.value is None:
        raise NodesError(f"{path}: key outputs.value: output form {output!r} writes the value at the current position")
    if output in ("line", "both") and nodes.outputs.line is None:
        raise NodesError(f"{path}: key outputs.line: output form {output!r} writes the error line (offset, slope, ref)")
    ins, outs = nodes.input_ids(), nodes.output_ids()
    both = sorted(set(ins.values()) & set(outs.values()))
    if both:
        raise NodesError(f"{path}: node(s) {both} are both an input and an output; the compensator never writes an input")
    dup = [n for n in set(outs.values()) if list(outs.values()).count(n) > 1]
    if dup:
        raise NodesError(f"{path}: key outputs: node(s) {sorted(dup)} named for more than one output")
    return nodes
