"""A strict YAML reader for files a user hands in (``metadata.yaml``).

:class:`StrictLoader` is a ``SafeLoader`` (libyaml's parser when present) that refuses
what a data file never needs and an attacker or a slip of the keyboard can abuse:

- aliases and anchors (``&a``, ``*a``): no alias expansion bomb ("billion laughs") can
  be built, and no value silently stands for another;
- merge keys (``<<:``);
- duplicate keys in a mapping (a second ``runs:`` entry for the same id would silently
  replace the first);
- explicit tags other than the core ones (``!!str !!int !!float !!bool !!null !!map
  !!seq``): no ``!!python/object``, ``!!binary``, ``!foo``;
- nesting deeper than :data:`~thermbench.data.limits.YAML_MAX_DEPTH` (no RecursionError),
  and more than :data:`~thermbench.data.limits.YAML_MAX_NODES` values (parsing time).

Two reading rules differ from PyYAML's YAML 1.1 ones: a date (``2024-03-04``) stays
text, and ``1e-5`` is a number, as in YAML 1.2 (PyYAML reads it as text).

:func:`load_yaml` returns the data and the line of every mapping key; every problem is a
:class:`YAMLInputError` whose message is one line with the line number.
"""

from __future__ import annotations

import re

import yaml
from yaml.composer import Composer
from yaml.constructor import ConstructorError
from yaml.events import AliasEvent, CollectionStartEvent, NodeEvent
from yaml.nodes import MappingNode

from .errors import DatasetError, one_line, short_repr
from .limits import YAML_MAX_DEPTH, YAML_MAX_NODES

_BASE = getattr(yaml, "CSafeLoader", yaml.SafeLoader)  # libyaml: about 4x faster
_CORE = "tag:yaml.org,2002:"
ALLOWED_TAGS = frozenset(_CORE + t for t in ("str", "int", "float", "bool", "null", "map", "seq"))
_MERGE = _CORE + "merge"


class YAMLInputError(DatasetError):
    """A YAML file breaks a rule of :class:`StrictLoader` or is not YAML; ``line`` is 1-based (or None).

    A :class:`~thermbench.data.errors.DatasetError` (a user's file, reported in one line)."""

    def __init__(self, problem: str, line: int | None = None):
        self.problem = one_line(problem)
        self.line = line
        super().__init__(self.problem if line is None else f"line {line}: {self.problem}")


def _line(mark) -> int | None:
    return None if mark is None else mark.line + 1


class StrictLoader(_BASE):
    """SafeLoader without aliases, anchors, merge keys, duplicate keys, non-core tags or deep nesting."""

    max_depth = YAML_MAX_DEPTH
    max_nodes = YAML_MAX_NODES

    # the Python composer on the (C) event stream: its compose_node is where events are checked
    compose_document = Composer.compose_document
    compose_scalar_node = Composer.compose_scalar_node
    compose_sequence_node = Composer.compose_sequence_node
    compose_mapping_node = Composer.compose_mapping_node
    get_single_node = Composer.get_single_node

    def __init__(self, stream):
        super().__init__(stream)
        self.anchors = {}
        self._depth = 0
        self._nodes = 0
        self.key_lines: dict[int, dict] = {}  # id(mapping) -> {key: line}
        self._keep: list = []  # the mappings above, alive while their ids are used

    def compose_node(self, parent, index):
        event = self.peek_event()
        if isinstance(event, AliasEvent):
            raise YAMLInputError(f"alias *{event.anchor} refused: a dataset file may not use aliases or anchors",
                                 _line(event.start_mark))  # fmt: skip
        if isinstance(event, NodeEvent) and event.anchor is not None:
            raise YAMLInputError(f"anchor &{event.anchor} refused: a dataset file may not use aliases or anchors",
                                 _line(event.start_mark))  # fmt: skip
        tag = getattr(event, "tag", None)
        if tag is not None and tag != "!" and tag not in ALLOWED_TAGS:
            tag = "!!" + tag[len(_CORE):] if tag.startswith(_CORE) else tag
            raise YAMLInputError(f"tag {short_repr(tag)} refused: only plain values (text, numbers, true/false, "
                                 "null, mappings, lists) are allowed", _line(event.start_mark))  # fmt: skip
        self._nodes += 1
        if self._nodes > self.max_nodes:
            raise YAMLInputError(f"more than {self.max_nodes} values: too many for a dataset's metadata",
                                 _line(event.start_mark))  # fmt: skip
        if isinstance(event, CollectionStartEvent):
            self._depth += 1
            if self._depth > self.max_depth:
                raise YAMLInputError(f"nested deeper than {self.max_depth} levels", _line(event.start_mark))
            try:
                return Composer.compose_node(self, parent, index)
            finally:
                self._depth -= 1
        return Composer.compose_node(self, parent, index)

    def _strict_mapping(self, node) -> tuple[dict, dict]:
        if not isinstance(node, MappingNode):
            raise ConstructorError(None, None, f"expected a mapping, found {node.id}", node.start_mark)
        mapping: dict = {}
        lines: dict = {}
        for key_node, value_node in node.value:
            if key_node.tag == _MERGE:
                raise YAMLInputError("merge key '<<' refused: write the keys out", _line(key_node.start_mark))
            key = self.construct_object(key_node, deep=True)
            try:
                hash(key)
            except TypeError:
                raise YAMLInputError(f"a list or mapping as a key ({short_repr(key)}) is not allowed",
                                     _line(key_node.start_mark)) from None  # fmt: skip
            if key in mapping:
                raise YAMLInputError(f"duplicate key {short_repr(key)} (first at line {lines[key]}): each key "
                                     "may appear once in a mapping", _line(key_node.start_mark))  # fmt: skip
            mapping[key] = self.construct_object(value_node)
            lines[key] = _line(key_node.start_mark)
        return mapping, lines

    def construct_yaml_map(self, node):
        data: dict = {}
        self._keep.append(data)
        yield data
        value, lines = self._strict_mapping(node)
        data.update(value)
        self.key_lines[id(data)] = lines

    def construct_yaml_int(self, node):
        try:
            return super().construct_yaml_int(node)
        except ValueError as exc:  # e.g. more digits than Python converts (4300)
            raise YAMLInputError(f"not an integer: {exc}", _line(node.start_mark)) from None

    def construct_yaml_bool(self, node):
        try:
            return super().construct_yaml_bool(node)
        except KeyError:  # !!bool on a non-boolean
            raise YAMLInputError(f"not a boolean: {short_repr(node.value)}", _line(node.start_mark)) from None

    def construct_yaml_float(self, node):
        try:
            return super().construct_yaml_float(node)
        except ValueError:  # !!float on a non-number
            raise YAMLInputError(f"not a number: {short_repr(node.value)}", _line(node.start_mark)) from None


StrictLoader.add_constructor(_CORE + "map", StrictLoader.construct_yaml_map)
StrictLoader.add_constructor(_CORE + "int", StrictLoader.construct_yaml_int)
StrictLoader.add_constructor(_CORE + "bool", StrictLoader.construct_yaml_bool)
StrictLoader.add_constructor(_CORE + "float", StrictLoader.construct_yaml_float)
# Implicit types: YAML 1.1's as PyYAML reads them, except that dates and '=' stay text,
# base-60 numbers (1:30) are text (1:0:0:...:0 would take minutes of big-integer
# arithmetic), and floats without a dot (1e-5) are numbers, as in YAML 1.2
StrictLoader.yaml_implicit_resolvers = {
    first: [(tag, rx) for tag, rx in resolvers if tag not in (_CORE + t for t in ("timestamp", "value", "int", "float"))]
    for first, resolvers in yaml.SafeLoader.yaml_implicit_resolvers.items()
}
StrictLoader.add_implicit_resolver(
    _CORE + "int",
    re.compile(r"^(?:[-+]?0b[0-1_]+|[-+]?0[0-7_]+|[-+]?(?:0|[1-9][0-9_]*)|[-+]?0x[0-9a-fA-F_]+)$"),
    list("-+0123456789"),
)
StrictLoader.add_implicit_resolver(
    _CORE + "float",
    re.compile(r"""^(?:[-+]?(?:[0-9][0-9_]*)\.[0-9_]*(?:[eE][-+]?[0-9]+)?
                  |[-+]?(?:[0-9][0-9_]*)[eE][-+]?[0-9]+
                  |\.[0-9_]+(?:[eE][-+][0-9]+)?
                  |[-+]?\.(?:inf|Inf|INF)
                  |\.(?:nan|NaN|NAN))$""", re.X),
    list("-+0123456789."),
)


class StrictDumper(yaml.SafeDumper):
    """A SafeDumper whose text round-trips through :class:`StrictLoader`: a string that the
    loader would read as a number (``1e5``, a hex digest of digits and one ``e``) is quoted."""


StrictDumper.yaml_implicit_resolvers = {k: list(v) for k, v in yaml.SafeDumper.yaml_implicit_resolvers.items()}
for _first, _resolvers in StrictLoader.yaml_implicit_resolvers.items():
    for _tag, _rx in _resolvers:
        StrictDumper.add_implicit_resolver(_tag, _rx, [_first])


def dump_yaml(data, **kw) -> str:
    """``yaml.safe_dump`` that :func:`load_yaml` reads back as written (see :class:`StrictDumper`)."""
    return yaml.dump(data, Dumper=StrictDumper, **kw)


def _key_lines(data, loader: StrictLoader) -> dict[tuple, int]:
    """Path of every mapping key (a tuple of keys and list indices) -> its line."""
    out: dict[tuple, int] = {}
    stack = [((), data)]
    while stack:
        path, node = stack.pop()
        if isinstance(node, dict):
            lines = loader.key_lines.get(id(node), {})
            for k, v in node.items():
                if k in lines:
                    out[path + (k,)] = lines[k]
                stack.append((path + (k,), v))
        elif isinstance(node, list):
            stack.extend((path + (i,), v) for i, v in enumerate(node))
    return out


def load_yaml(text: str) -> tuple[object, dict[tuple, int]]:
    """Parse one YAML document with :class:`StrictLoader`: ``(data, key_lines)`` where
    ``key_lines`` maps the path of every mapping key to its 1-based line. Raises
    :class:`YAMLInputError` (one line, with the line number) for any problem."""
    loader = StrictLoader(text)
    try:
        data = loader.get_single_data()
        return data, _key_lines(data, loader)
    except YAMLInputError:
        raise
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        problem = "; ".join(p for p in (exc.context, exc.problem) if p) or "not valid YAML"
        line = _line(mark)
        if "maximum nesting depth" in problem:  # PyYAML >= 6.0.4 stops deep nesting in its scanner, before the composer
            raise YAMLInputError(f"nested deeper than {StrictLoader.max_depth} levels", line) from None
        if line is not None and text.split("\n", line)[min(line, text.count("\n") + 1) - 1].startswith("\t"):
            problem += " (a tab: indent YAML with spaces)"
        raise YAMLInputError(f"not valid YAML: {problem}", line) from None
    except yaml.reader.ReaderError as exc:
        line = text.count("\n", 0, exc.position) + 1 if isinstance(exc.position, int) else None
        raise YAMLInputError(f"not valid YAML: character {short_repr(chr(exc.character)) if isinstance(exc.character, int) else short_repr(exc.character)} is not allowed", line) from None  # fmt: skip
    except yaml.YAMLError as exc:
        raise YAMLInputError(f"not valid YAML: {exc}") from None
    except RecursionError:  # not reached with the depth cap; kept as a last guard
        raise YAMLInputError(f"nested too deeply (more than {YAML_MAX_DEPTH} levels)") from None
    finally:
        loader.dispose()
