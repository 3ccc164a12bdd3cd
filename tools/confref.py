"""The configuration reference (``docs/configuration.md``), generated from ``conf/``.

    python -m tools.confref                 # (re)write docs/configuration.md
    python -m tools.confref --check         # exit 1 if the committed file is stale

One section per primary config (``conf/*.yaml``: the command that composes it, its defaults
list, every key with its default and its comment), then one per config group (every directory
of ``conf/`` holding options, recursively: ``machine/``, ``hydra/launcher/``, ...): each option's
header comment, ``_target_``, defaults list and keys.

The comments are the point, so the YAML is read with ruamel.yaml's round-trip loader, which keeps
every comment with its line and column (and every key and list item with its line). ruamel attaches
a comment written on its own line to the *previous* key's end-of-line comment; this module instead
places each comment by its position, as a reader of the file does:

* comment lines before the first key: the file's header (``# @package X`` is the package directive;
  lines indented after ``#`` — ``#   thermbench train ...`` — are examples, shown as code);
* a comment after a value on the same line: that key's comment; following comment-only lines that
  start in the same column continue it;
* comment-only lines above a key (or list item): that key's comment (written before the line's own);
* comment lines after the last key: a closing note of the file.

Values are shown as written (``11.7e-6`` stays ``11.7e-6``); nested block mappings are flattened
to dotted paths (``numerics.dx_m``), list items of block lists to ``steps[0]``; flow collections
(``{start: 0.0, stop: 500.0}``, ``[a, b]``) are one value, shortened past ``MAX_VALUE_CHARS``.
"""

from __future__ import annotations

import argparse
import io
import re
import sys
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ruamel.yaml import YAML
from ruamel.yaml.comments import CommentedMap, CommentedSeq
from ruamel.yaml.tokens import CommentToken

#: the command that regenerates the reference (stated in its first line)
COMMAND = "python -m tools.confref"
#: the reference's place, relative to the project root (the parent of conf/)
DEFAULT_OUT = Path("docs") / "configuration.md"
#: a flow value (list or mapping) rendered longer than this is shortened: "[a, b, … (12 items)]"
MAX_VALUE_CHARS = 100

#: primary config (conf/<name>.yaml) -> how it is used; the order is the reference's order.
#: A primary config missing here is listed as "not known to tools.confref" (a test fails).
COMMANDS: dict[str, str] = {
    "simulate": "`thermbench simulate [overrides]` (`thermbench.cli`); also the base of every standard "
    "benchmark dataset (`thermbench.bench.datasets`)",
    "benchmark_datasets": "not composed by Hydra: read as plain YAML by `thermbench.bench.datasets` "
    "(`load_benchmark`, `thermbench simulate suite=benchmark`); each entry is a list of overrides "
    "of `simulate.yaml`",
    "train": "`thermbench train [overrides] [-m]` (Hydra job, `thermbench.app`)",
    "evaluate": "`thermbench evaluate [overrides] [-m]` (Hydra job, `thermbench.app`)",
    "benchmark": "`thermbench benchmark [overrides] [-m]` (Hydra job, `thermbench.app`)",
    "export": "`thermbench export [overrides] [-m]` (Hydra job, `thermbench.app`)",
    "diagnose": "`thermbench diagnose DATA_DIR --out OUT_DIR [overrides]` (`thermbench.cli`, "
    "`thermbench.discrepancy`)",
    "compensator": "`thermbench compensator MODEL_DIR --endpoint URL --nodes nodes.yaml [overrides]` "
    "(`thermbench.compensator.client`)",
    "sim_cnc": "`thermbench sim-cnc [--endpoint URL] [overrides]` (`thermbench.compensator.simcnc`)",
    "linuxcnc_component": "`thermbench linuxcnc component MODEL_DIR [overrides]`, a HAL component started by "
    "LinuxCNC's `loadusr` (`thermbench.linuxcnc.component`)",
    "linuxcnc_plant": "`thermbench linuxcnc plant [overrides]`, a HAL component of the sim configuration "
    "(`thermbench.linuxcnc.plant`)",
    "linuxcnc_sim": "`thermbench linuxcnc sim MODEL_DIR [overrides]` (`thermbench.linuxcnc.sim`)",
}
UNKNOWN_COMMAND = "not known to `tools.confref` (add it to `COMMANDS`)"

INTRO = """\
The configuration is [Hydra](https://hydra.cc)'s: a *primary config* (`conf/<name>.yaml`) composes
options of *config groups* (`conf/<group>/<option>.yaml`) through its defaults list, then its own
keys. On the command line, `group=option` picks an option and `path=value` sets a key, e.g.
`thermbench simulate machine=seed002_vmc655h_x numerics.dx_m=0.005`; `-m` with comma-separated
values sweeps (Hydra jobs). `???` marks a value that must be given; `${...}` is an interpolation,
resolved when the config is composed. In the defaults lists, later entries override earlier ones
and `_self_` is the place of the file's own keys.

Each key below is shown with its path in the composed config (as `path=value` names it), its default
as written in the YAML and the comment written beside or above it. Nested mappings are flattened to
dotted paths, items of block lists to `path[i]`; long lists are shortened (`… (N items)`)."""


# ----------------------------------------------------------------------------- reading a file


@dataclass
class Entry:
    """A key (or block-list item) of a config file."""

    path: tuple  # keys (str) and list indices (int) from the file's root
    line: int  # 0-based line of the key / item
    value: Any
    leaf: bool  # shown as one value (scalar, flow collection, list of scalars, empty)
    comments: list[str] = field(default_factory=list)  # above comments, then the line's own


@dataclass
class ConfFile:
    rel: str  # path under conf/, with '/'
    header: list[str]  # comment lines (text after '#') of the header, '' for a blank line
    package: str | None  # '# @package X'
    entries: list[Entry]  # document order
    footer: list[str]


_yaml = YAML(typ="rt")
_dumper = YAML(typ="rt")
_dumper.width = 1_000_000


def _comment_tokens(node: Any, out: list[CommentToken], seen: set[int]) -> None:
    if id(node) in seen:
        return
    seen.add(id(node))
    ca = getattr(node, "ca", None)

    def grab(x: Any) -> None:
        if isinstance(x, CommentToken):
            out.append(x)
        elif isinstance(x, (list, tuple)):
            for e in x:
                grab(e)

    if ca is not None:
        grab(ca.comment)
        grab(list(ca.items.values()))
        grab(getattr(ca, "end", None))
    if isinstance(node, dict):
        for v in node.values():
            _comment_tokens(v, out, seen)
    elif isinstance(node, list):
        for v in node:
            _comment_tokens(v, out, seen)


def _comment_lines(root: Any, raw: list[str], rel: str) -> dict[int, tuple[int, str]]:
    """line -> (column of '#', text after '#') of every comment ruamel kept.

    A token's value may start with the newlines before its first comment; its start mark is the
    position of that first '#'. Every position is checked against the file's text."""
    toks: list[CommentToken] = []
    _comment_tokens(root, toks, set())
    found: dict[int, tuple[int, str]] = {}
    for tok in toks:
        pieces = tok.value.split("\n")
        first = next((i for i, p in enumerate(pieces) if p.strip().startswith("#")), None)
        if first is None:
            continue
        for i, piece in enumerate(pieces):
            stripped = piece.strip()
            if not stripped.startswith("#"):
                continue  # a blank line kept with the comment
            line = tok.start_mark.line + i - first
            col = tok.start_mark.column if i == first else len(piece) - len(piece.lstrip())
            if line >= len(raw) or not raw[line][col:].startswith(stripped):
                raise ValueError(f"conf/{rel}: comment {stripped!r} is not at line {line + 1}, column {col + 1} "
                                 f"as ruamel.yaml says (a ruamel.yaml change?)")
            found[line] = (col, stripped[1:].rstrip())
    for i, text in enumerate(raw):  # ruamel.yaml drops some comments inside flow collections
        col = _comment_column(text)
        if col is not None and i not in found:
            warnings.warn(f"conf/{rel}:{i + 1}: comment not kept by ruamel.yaml (inside a flow collection?), "
                          f"left out of the reference: {text[col:].strip()}", stacklevel=2)
    return found


def _comment_column(line: str) -> int | None:
    """Column of a '#' that starts a comment on ``line`` (outside quotes, after a blank), else None."""
    quote = None
    for i, ch in enumerate(line):
        if quote:
            if ch == quote:
                quote = None
        elif ch in "'\"" and (i == 0 or line[i - 1] in " \t[{,:-"):
            quote = ch
        elif ch == "#" and (i == 0 or line[i - 1] in " \t"):
            return i
    return None


def _is_flow(node: Any) -> bool:
    return bool(node.fa.flow_style()) or len(node) == 0


def _entries(node: Any, path: tuple, out: list[Entry], owner: dict[int, list[tuple]]) -> None:
    """Entries of block collection ``node`` (document order); ``owner``: line -> entry paths starting there."""

    def add(p: tuple, line: int, value: Any) -> None:
        block = isinstance(value, (CommentedMap, CommentedSeq)) and not _is_flow(value)
        scalars_only = (isinstance(value, CommentedSeq) and not any(isinstance(v, (dict, list)) for v in value)
                        and p != ("defaults",))  # a defaults list is shown item by item
        leaf = not block or scalars_only
        out.append(Entry(p, line, value, leaf))
        owner.setdefault(line, []).append(p)
        if block and scalars_only:
            for i in range(len(value)):  # a comment at an item belongs to the list
                owner.setdefault(value.lc.item(i)[0], []).append(p)
        elif block:
            _entries(value, p, out, owner)

    if isinstance(node, CommentedMap):
        for k, v in node.items():
            add((*path, k), node.lc.key(k)[0], v)
    elif isinstance(node, CommentedSeq):
        for i, v in enumerate(node):
            add((*path, i), node.lc.item(i)[0], v)


def read_conf(path: Path, rel: str) -> ConfFile:
    text = path.read_text(encoding="utf-8")
    raw = text.splitlines()
    root = _yaml.load(text)
    entries: list[Entry] = []
    owner: dict[int, list[tuple]] = {}
    if root is None:  # comments only: every non-blank line is a comment (else there would be content)
        comments = {i: (len(r) - len(r.lstrip()), r.strip()[1:]) for i, r in enumerate(raw) if r.strip()}
    else:
        comments = _comment_lines(root, raw, rel)
        _entries(root, (), entries, owner)
    by_path = {e.path: e for e in entries}
    starts = sorted(owner)
    first = starts[0] if starts else len(raw)

    def content_before(i: int) -> bool:
        col = comments[i][0]
        return bool(raw[i][:col].strip())

    def owner_at_or_before(i: int) -> tuple | None:
        cands = [s for s in starts if s <= i]
        return max(owner[cands[-1]], key=len) if cands else None

    header: list[str] = []
    footer: list[str] = []
    eol: dict[tuple, list[str]] = {}
    pre: dict[tuple, list[str]] = {}
    last_eol: tuple[int, int, tuple] | None = None  # (line, column, path) of the last end-of-line comment
    for i in sorted(comments):
        col, body = comments[i]
        if content_before(i):
            p = owner_at_or_before(i)
            if p is not None:
                eol.setdefault(p, []).append(body.strip())
                last_eol = (i, col, p)
            continue
        if last_eol and i == last_eol[0] + 1 and col == last_eol[1] and col > 0:  # continues the line above
            eol[last_eol[2]].append(body.strip())
            last_eol = (i, col, last_eol[2])
            continue
        if i < first:
            header.append(i)
            continue
        nxt = [s for s in starts if s > i]
        if nxt:
            pre.setdefault(min(owner[nxt[0]], key=len), []).append(body.strip())
        else:
            footer.append(body)

    # the header: comment lines before the first key; a block right above the first key (no blank
    # line between) after an earlier block belongs to that key
    blocks: list[list[int]] = []
    for i in header:
        if blocks and i == blocks[-1][-1] + 1:
            blocks[-1].append(i)
        else:
            blocks.append([i])
    if len(blocks) > 1 and starts and blocks[-1][-1] == first - 1:
        key_block = blocks.pop()
        p = min(owner[first], key=len)
        pre[p] = [comments[i][1].strip() for i in key_block] + pre.get(p, [])
    header_lines: list[str] = []
    package = None
    for b, block in enumerate(blocks):
        if b:
            header_lines.append("")
        for i in block:
            body = comments[i][1]
            m = re.match(r"\s*@package\s+(\S+)", body)
            if m:
                package = m.group(1)
                continue
            header_lines.append(body)
    for p, e in by_path.items():
        e.comments = pre.get(p, []) + eol.get(p, [])
    return ConfFile(rel, header_lines, package, entries, footer)


# ----------------------------------------------------------------------------- rendering values


def _scalar(v: Any) -> str:
    if v is None:
        return "null"
    if isinstance(v, bool):
        return "true" if v else "false"
    buf = io.StringIO()
    _dumper.dump(v, buf)
    s = buf.getvalue()
    if s.endswith("\n...\n"):
        s = s[: -len("\n...\n")]
    return " ".join(s.split())


def render_value(v: Any, limit: int = MAX_VALUE_CHARS) -> str:
    """``v`` as YAML flow text, shortened past ``limit`` characters."""
    if isinstance(v, dict):
        parts = [f"{_scalar(k)}: {render_value(x, 10**9)}" for k, x in v.items()]
        return _join(parts, "{", "}", "keys", limit)
    if isinstance(v, list):
        return _join([render_value(x, 10**9) for x in v], "[", "]", "items", limit)
    return _scalar(v)


def _join(parts: list[str], open_: str, close: str, noun: str, limit: int) -> str:
    full = open_ + ", ".join(parts) + close
    if len(full) <= limit:
        return full
    shown: list[str] = []
    for p in parts:
        if len(open_ + ", ".join([*shown, p])) > limit * 2 // 3 and shown:
            break
        shown.append(p)
    return f"{open_}{', '.join(shown)}, …{close} ({len(parts)} {noun})"


def _key_segment(k: Any) -> str:
    k = str(k)
    return k if re.fullmatch(r"[A-Za-z0-9_\-]+", k) else f'"{k}"'


def dotted(prefix: str, path: tuple) -> str:
    out = prefix
    for p in path:
        if isinstance(p, int):
            out += f"[{p}]"
        else:
            out = f"{out}.{_key_segment(p)}" if out else _key_segment(p)
    return out


# ----------------------------------------------------------------------------- Markdown


def md_text(s: str, table: bool = False) -> str:
    """Comment prose as Markdown: code spans kept, characters Markdown would act on escaped
    (``table``: also '|', which would end the cell, inside code spans too)."""
    parts = s.split("`")
    if len(parts) % 2 == 0:  # unbalanced backticks: none is a code span
        parts = [s]
    out = []
    for n, part in enumerate(parts):
        if n % 2:
            out.append(md_code(part, table))
            continue
        part = part.replace("\\", "\\\\").replace("`", "\\`").replace("*", "\\*").replace("<", "\\<")
        part = re.sub(r"(?<![A-Za-z0-9])_|_(?![A-Za-z0-9])", r"\\_", part)  # intraword _ is never emphasis
        out.append(part.replace("|", "\\|") if table else part)
    text = "".join(out)
    if not table:  # a paragraph must not start a heading, quote, list or rule
        if re.match(r"[#>+=*-]", text):
            text = "\\" + text
        text = re.sub(r"^(\d+)([.)])", r"\1\\\2", text)  # "1. " / "1) " start a list; a digit cannot be escaped
    return text


def md_code(s: str, table: bool = False) -> str:
    """``s`` as an inline code span (``table``: '|' escaped, as a table cell needs)."""
    tick = "``" if "`" in s else "`"
    pad = " " if tick == "``" else ""
    span = f"{tick}{pad}{s}{pad}{tick}"
    return span.replace("|", "\\|") if table else span


def _one_line(comments: list[str], table: bool = False) -> str:
    return md_text(" ".join(" ".join(c.split()) for c in comments if c.strip()), table)


def slug(heading: str) -> str:
    """GitHub's anchor for a heading."""
    s = re.sub(r"[^\w\- ]", "", heading.lower())
    return s.replace(" ", "-")


def _header_md(lines: list[str]) -> list[str]:
    """Header comment lines -> paragraphs (prose) and code blocks (lines indented after '#')."""
    out: list[str] = []
    para: list[str] = []
    code: list[str] = []

    def flush() -> None:
        if para:
            text = md_text(" ".join(para[0].split()))
            for prev, line in zip(para, para[1:]):
                # a line that ends without punctuation before a new sentence ("... [overrides]" /
                # "Find where ..."): a line break, not a space
                brk = not re.search(r"[.,;:!?]$", prev.rstrip()) and re.match(r"[A-Z][a-z]*\s", line)
                text += ("\\\n" if brk else " ") + md_text(" ".join(line.split()))
            out.extend([text, ""])
            para.clear()
        if code:
            ind = min(len(c) - len(c.lstrip()) for c in code)
            out.extend(["```text", *[c[ind:].rstrip() for c in code], "```", ""])
            code.clear()

    for ln in lines:
        body = ln[1:] if ln.startswith(" ") else ln
        if not body.strip():
            flush()
        elif body.startswith(" "):
            if para:
                flush()
            code.append(body)
        else:
            if code:
                flush()
            para.append(body)
    flush()
    return out


class _Doc:
    def __init__(self) -> None:
        self.lines: list[str] = []

    def heading(self, level: int, text: str) -> None:
        self.lines.extend(["#" * level + " " + text, ""])

    def add(self, *lines: str) -> None:
        self.lines.extend(lines)


@dataclass
class _DefaultEntry:
    shown: str  # the entry as written
    kind: str  # "group" / "optional" / "override" / "config" (a config of this directory) / "self"
    group: str | None  # the group it picks from, relative to conf/
    target: str | None  # the file it names, relative to conf/ (None: no option / _self_)


def _default_entries(cf: ConfFile) -> list[_DefaultEntry]:
    """The defaults list of ``cf``, resolved as Hydra does: group names relative to the file's
    directory unless absolute (``/dataset``); a bare name is a config of the same directory."""
    top = next((e for e in cf.entries if e.path == ("defaults",)), None)
    if top is None or not isinstance(top.value, list):
        return []
    here = Path(cf.rel).parent.as_posix()
    here = "" if here == "." else here
    out = []
    for item in top.value:
        if isinstance(item, dict) and len(item) == 1:
            key, opt = next(iter(item.items()))
            words = str(key).split()
            group = words[-1].split("@")[0]
            group = group[1:] if group.startswith("/") else "/".join(x for x in (here, group) if x)
            kind = "override" if "override" in words else "optional" if "optional" in words else "group"
            target = f"{group}/{opt}.yaml" if opt is not None else None
            out.append(_DefaultEntry(f"{key}: {_scalar(opt)}", kind, group, target))
        elif item == "_self_":
            out.append(_DefaultEntry("_self_", "self", None, None))
        else:
            name = "/".join(x for x in (here, str(item)) if x)
            out.append(_DefaultEntry(_scalar(item), "config", None, f"{name}.yaml"))
    return out


def _defaults_items(cf: ConfFile, conf: Path, anchors: dict[str, str]) -> tuple[list[str], list[str]]:
    """(Markdown bullets of the defaults list, comments on the ``defaults`` key itself)."""
    entries = _default_entries(cf)
    if not entries:
        return [], []
    bullets = []
    for i, d in enumerate(entries):
        comments = [c for e in cf.entries if e.path[:2] == ("defaults", i) for c in e.comments]
        if d.target is not None:
            if d.target in anchors:
                note = f"[`{d.target}`](#{anchors[d.target]})"
            elif (conf / d.target).exists():
                note = f"`{d.target}`"
            else:
                note = f"`{d.target}` is not in `conf/`: Hydra finds it on its search path (an installed plugin)"
        elif d.kind == "self":
            note = "this file's own keys"
        else:
            group = f"[`{d.group}/`](#{anchors[d.group + '/']})" if d.group + "/" in anchors else f"`{d.group}/`"
            note = f"none by default; options: {group}"
        line = f"- {md_code(d.shown)} → {note}"
        if comments:
            line += f" — {_one_line(comments)}"
        bullets.append(line)
    top = next(e for e in cf.entries if e.path == ("defaults",))
    return bullets, top.comments


def _keys_table(cf: ConfFile, prefix: str, skip_target: bool) -> list[str]:
    rows = []
    for e in cf.entries:
        if e.path and e.path[0] == "defaults":
            continue
        if skip_target and e.path == ("_target_",):
            continue
        if not e.leaf and not e.comments:
            continue
        default = md_code(render_value(e.value), table=True) if e.leaf else ""
        rows.append(f"| {md_code(dotted(prefix, e.path), True)} | {default} | {_one_line(e.comments, True)} |")
    if not rows:
        return []
    return ["| Key | Default | Comment |", "| --- | --- | --- |", *rows, ""]


def _conf_body(doc: _Doc, cf: ConfFile, conf: Path, prefix: str, anchors: dict[str, str]) -> None:
    doc.add(*_header_md(cf.header))
    target = next((e for e in cf.entries if e.path == ("_target_",)), None)
    if target is not None:
        note = f" — {_one_line(target.comments)}" if target.comments else ""
        doc.add(f"Target: {md_code(str(target.value))}{note}", "")
    if cf.package is not None:
        where = "the top level of the composed config" if prefix == "" else md_code(prefix)
        doc.add(f"Package: {md_code(cf.package)} (its keys go to {where}).", "")
    bullets, dcomments = _defaults_items(cf, conf, anchors)
    if bullets:
        doc.add("Defaults list" + (f" ({_one_line(dcomments)})" if dcomments else "") + ":", "", *bullets, "")
    table = _keys_table(cf, prefix, skip_target=target is not None)
    if table:
        doc.add(*table)
    elif not bullets:
        doc.add("No keys.", "")
    if any(f.strip() for f in cf.footer):
        doc.add(f"Closing comment: {_one_line(cf.footer)}", "")


def _package_prefix(package: str | None, group: str) -> str:
    if package is None or package == "_group_":
        return group.replace("/", ".")
    if package == "_global_":
        return ""
    return package.removeprefix("_global_.").replace("_group_", group.replace("/", "."))


def reference_markdown(conf_dir: str | Path | None = None) -> str:
    """The configuration reference of ``conf_dir`` (default: ``thermbench.config.config_dir()``)."""
    if conf_dir is None:
        from thermbench.config import config_dir

        conf_dir = config_dir()
    conf = Path(conf_dir)
    primary_paths = sorted(conf.glob("*.yaml"))
    order = {name: i for i, name in enumerate(COMMANDS)}
    primary_paths.sort(key=lambda p: (order.get(p.stem, len(order)), p.stem))
    groups: dict[str, list[Path]] = {}
    for p in sorted(conf.rglob("*.yaml")):
        rel = p.relative_to(conf)
        if len(rel.parts) > 1:
            groups.setdefault("/".join(rel.parts[:-1]), []).append(p)
    primaries = [read_conf(p, p.name) for p in primary_paths]
    options = {g: [read_conf(p, p.relative_to(conf).as_posix()) for p in ps] for g, ps in groups.items()}

    # anchors are known before rendering (the defaults lists link forward)
    doc = _Doc()
    plan: list[tuple[int, str, str]] = [(1, "Configuration reference", "")]
    plan.append((2, "Primary configs", ""))
    plan += [(3, f"`{cf.rel}`", cf.rel) for cf in primaries]
    plan.append((2, "Config groups", ""))
    for g in sorted(options):
        plan.append((3, f"Group `{g}`", g + "/"))
        plan += [(4, f"`{cf.rel}`", cf.rel) for cf in options[g]]
    anchors: dict[str, str] = {}
    seen: dict[str, int] = {}
    for _, text, key in plan:
        base = slug(text)
        n = seen.get(base, 0)
        seen[base] = n + 1
        if key:
            anchors[key] = base if n == 0 else f"{base}-{n}"

    # which configs pick an option of each group
    picked: dict[str, list[str]] = {}
    default_option: dict[str, set[str]] = {}
    for cf in [*primaries, *[o for os_ in options.values() for o in os_]]:
        for d in _default_entries(cf):
            if d.group is None:
                continue
            if d.kind == "group" and d.target is not None:
                default_option.setdefault(d.group, set()).add(Path(d.target).stem)
            opt = "none" if d.target is None else md_code(Path(d.target).stem)
            how = {"override": f"overrides it with {opt}", "optional": f"optional, default {opt}"}.get(
                d.kind, f"default {opt}")
            picked.setdefault(d.group, []).append(f"[`{cf.rel}`](#{anchors[cf.rel]}) ({how})")

    doc.heading(1, "Configuration reference")
    doc.add(f"*Generated from `conf/` by `{COMMAND}`: do not edit by hand. Edit the comments in `conf/` and "
            f"regenerate; `{COMMAND} --check` (run by `tests/test_confref.py`) fails when this file is stale.*", "")
    doc.add(INTRO, "")
    doc.add("Primary configs: " + ", ".join(f"[`{cf.rel}`](#{anchors[cf.rel]})" for cf in primaries) + ".", "")
    doc.add("Config groups: " + ", ".join(f"[`{g}/`](#{anchors[g + '/']})" for g in sorted(options)) + ".", "")

    doc.heading(2, "Primary configs")
    for cf in primaries:
        doc.heading(3, f"`{cf.rel}`")
        stem = Path(cf.rel).stem
        doc.add(f"Used by: {COMMANDS.get(stem, UNKNOWN_COMMAND)}.", "")
        _conf_body(doc, cf, conf, "", anchors)

    doc.heading(2, "Config groups")
    doc.add("Each option of a group is one file. Keys are shown with their path in the composed config "
            "(under the group's package, `<group>.` unless the option's header says `# @package _global_`).", "")
    for g in sorted(options):
        doc.heading(3, f"Group `{g}`")
        names = [Path(cf.rel).stem for cf in options[g]]
        links = ", ".join(f"[`{n}`](#{anchors[cf.rel]})" for n, cf in zip(names, options[g]))
        example = next((n for n in names if n not in default_option.get(g, ())), names[0])
        doc.add(f"Options (`conf/{g}/`): {links}. Choose one with `{g}={example}`.", "")
        if g in picked:
            doc.add("Picked by: " + "; ".join(picked[g]) + ".", "")
        else:
            doc.add("No defaults list picks this group: it is chosen on the command line only.", "")
        for cf in options[g]:
            doc.heading(4, f"`{cf.rel}`")
            _conf_body(doc, cf, conf, _package_prefix(cf.package, g), anchors)

    text = "\n".join(doc.lines).rstrip("\n") + "\n"
    return re.sub(r"\n{3,}", "\n\n", text)


# ----------------------------------------------------------------------------- command line


def main(argv: list[str] | None = None) -> int:
    from thermbench.outputs import write_text_atomic
    from thermbench.config import config_dir

    parser = argparse.ArgumentParser(prog=COMMAND, description=__doc__.splitlines()[0])
    parser.add_argument("--out", default=None, help=f"the Markdown file (default: <project>/{DEFAULT_OUT.as_posix()})")
    parser.add_argument("--check", action="store_true",
                        help="write nothing; exit 1 if --out differs from the generated text")
    parser.add_argument("--conf-dir", default=None,
                        help="the config directory (default: thermbench.config.config_dir())")
    args = parser.parse_args(argv)
    conf = Path(args.conf_dir) if args.conf_dir else config_dir()
    out = Path(args.out) if args.out else conf.parent / DEFAULT_OUT
    text = reference_markdown(conf)
    if args.check:
        current = out.read_text(encoding="utf-8") if out.exists() else None
        if current != text:
            what = "is missing" if current is None else "is stale"
            print(f"{out} {what}: regenerate it with `{COMMAND}`", file=sys.stderr)
            return 1
        print(f"{out} is up to date")
        return 0
    write_text_atomic(out, text)
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
