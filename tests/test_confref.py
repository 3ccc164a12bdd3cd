"""docs/configuration.md is generated from conf/ (tools.confref) and must never go stale."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from tools import confref
from thermbench.config import config_dir

CONF = config_dir()
DOC = CONF.parent / "docs" / "configuration.md"


@pytest.fixture(scope="module")
def generated() -> str:
    return confref.reference_markdown()


def _rows(text: str) -> set[str]:
    return set(text.splitlines())


def test_committed_reference_is_current(generated):
    # (a) regenerate with: python -m tools.confref
    assert DOC.exists(), "docs/configuration.md is missing: run python -m tools.confref"
    stale = "docs/configuration.md is stale: run python -m tools.confref"
    assert DOC.read_text(encoding="utf-8") == generated, stale
    assert generated.splitlines()[2].startswith("*Generated from `conf/` by `python -m tools.confref`")


def test_every_conf_file_has_a_section(generated):
    # (b) a primary config is a level-3 heading, a group option a level-4 one
    lines = _rows(generated)
    files = sorted(CONF.rglob("*.yaml"))
    assert len(files) > 40
    for p in files:
        rel = p.relative_to(CONF).as_posix()
        level = "###" if "/" not in rel else "####"
        assert f"{level} `{rel}`" in lines, rel
    for group in {p.relative_to(CONF).parent.as_posix() for p in files} - {"."}:
        assert f"### Group `{group}`" in lines, group


def test_every_primary_config_names_its_command(generated):
    assert {p.stem for p in CONF.glob("*.yaml")} <= set(confref.COMMANDS)
    assert confref.UNKNOWN_COMMAND not in generated


def test_known_keys_defaults_and_comments(generated):
    # (c) each line below can be read off the YAML itself
    lines = _rows(generated)
    expected = [
        "| `numerics.dx_m` | `0.01` | seed 000 Table 1 |",  # simulate.yaml
        "| `seed` | `0` | every random draw (noise, artefacts, random duty) comes from here |",  # simulate.yaml
        "| `max_effects` | `3` | add at most this many effects |",  # diagnose.yaml
        "| `file_format` | `csv` | csv \\| parquet |",  # simulate.yaml: '|' escaped in a table cell
        "| `machine.material.alpha_per_K` | `11.7e-6` |  |",  # machine/seed000_x.yaml: as written
        "| `machine.ambient_C` | `14.5` | seed 002 Table 4 ambient |",  # machine/seed002_vmc655h_x.yaml
        "| `tracking.artifact_root` | `null` | the server decides |",  # tracking/server.yaml
        "| `hydra.launcher.cpus_per_task` | `2` |  |",  # hydra/launcher/cluster.yaml: package hydra.launcher
        "| `numerics.dx_m` | `0.005` |  |",  # truth/benchmark.yaml: @package _global_
        "| `preprocess.steps[1].R` | `8.8706` |  |",  # preprocess/default.yaml: a list of mappings
        "Target: `thermbench.models.lssvm.PSOLSSVM`",  # model/lssvm.yaml
        "- `truth: none` → [`truth/none.yaml`](#truthnoneyaml) — after \\_self\\_: the truth overrides numerics "
        "and effects",  # simulate.yaml defaults list
    ]
    for line in expected:
        assert line in lines, line
    # compensator.yaml: a comment continued on the next line, in the same column
    clock = next(ln for ln in lines if ln.startswith("| `clock` | `source` |"))
    assert "(servers that stamp every sample, sim-cnc); client = this computer's clock" in clock
    # dataset/fl_thermal.yaml: 17 benchmark families (count them in the YAML) are more than a table cell shows
    assert any(ln.startswith("| `dataset.benchmark_families` | `[mlr_seed002, lssvm, ") and "(17 items)" in ln
               for ln in lines)  # fmt: skip


def _unescape(md: str) -> str:
    return " ".join(re.sub(r"\\(.)", r"\1", md, flags=re.S).split())


def _comment(line: str) -> str | None:
    """The comment of a YAML line: after a '#' that starts a line or follows a blank, outside
    a quoted value (a quote opens only where a value starts)."""
    quote = None
    for i, ch in enumerate(line):
        if quote:
            quote = None if ch == quote else quote
        elif ch in "\"'" and (i == 0 or line[i - 1] in " :[{,"):
            quote = ch
        elif ch == "#" and (i == 0 or line[i - 1].isspace()):
            return line[i + 1 :]
    return None


def test_comment_scan_skips_hashes_in_quoted_values():
    assert _comment('notes: "condition #1 (50 mm)"  # Table 5') == " Table 5"
    assert _comment("a: 1  # the machine's axis") == " the machine's axis"
    assert _comment("# header") == " header"
    assert _comment("url: http://x/#frag") is None


def test_no_comment_is_lost(generated):
    # every comment in conf/ (found here by a plain scan of the lines) is in the reference
    doc = _unescape(generated)
    n = 0
    for p in sorted(CONF.rglob("*.yaml")):
        for raw in p.read_text(encoding="utf-8").splitlines():
            text = _comment(raw)
            if not text or not text.strip() or "@package" in text:
                continue
            n += 1
            assert " ".join(text.split()) in doc, f"{p.relative_to(CONF)}: {raw.strip()}"
    assert n > 150


def test_links_point_at_headings(generated):
    def github_slug(heading: str) -> str:
        return re.sub(r"[^a-z0-9_\- ]", "", heading.lower()).replace(" ", "-")

    anchors = {github_slug(m.group(1)) for m in re.finditer(r"^#+ (.+)$", generated, flags=re.M)}
    targets = set(re.findall(r"\]\(#([^)]*)\)", generated))
    assert targets and targets <= anchors, sorted(targets - anchors)


TINY = """\
# tiny: a primary config for the test.
#   thermbench tiny size_mm=4
defaults:
  - colour: red        # the default colour
  - _self_

size_mm: 3             # how big
nested:
  depth_m: 0.5         # deep
  when: ${now:%H}
# the speed, above its key
speed: 1.0e-3
long: [aaaaaaaaaa, bbbbbbbbbb, cccccccccc, dddddddddd, eeeeeeeeee, ffffffffff, gggggggggg, hhhhhhhhhh, iiiiiiiiii]
note: 2                # first line
                       # second line
"""
RED = """\
# @package _global_
# A red option.
_target_: pkg.Red
shade: 0.9   # how _red_ | very
"""
BLUE = """\
# A blue option.
shade: 0.1
"""


@pytest.fixture
def tiny_conf(tmp_path) -> Path:
    conf = tmp_path / "conf"
    (conf / "colour").mkdir(parents=True)
    (conf / "tiny.yaml").write_text(TINY, encoding="utf-8")
    (conf / "colour" / "red.yaml").write_text(RED, encoding="utf-8")
    (conf / "colour" / "blue.yaml").write_text(BLUE, encoding="utf-8")
    return conf


def test_tiny_conf_renders_expected_lines(tiny_conf):
    # (d) expectations written by hand from TINY / RED / BLUE above
    text = confref.reference_markdown(tiny_conf)
    lines = text.splitlines()
    for line in [
        "### `tiny.yaml`",
        "Used by: not known to `tools.confref` (add it to `COMMANDS`).",
        "tiny: a primary config for the test.",
        "thermbench tiny size_mm=4",
        "- `colour: red` → [`colour/red.yaml`](#colourredyaml) — the default colour",
        "- `_self_` → this file's own keys",
        "| `size_mm` | `3` | how big |",
        "| `nested.depth_m` | `0.5` | deep |",
        "| `nested.when` | `${now:%H}` |  |",
        "| `speed` | `1.0e-3` | the speed, above its key |",
        "| `note` | `2` | first line second line |",
        "### Group `colour`",
        "Picked by: [`tiny.yaml`](#tinyyaml) (default `red`).",
        "#### `colour/red.yaml`",
        "A red option.",
        "Target: `pkg.Red`",
        "Package: `_global_` (its keys go to the top level of the composed config).",
        "| `shade` | `0.9` | how \\_red\\_ \\| very |",
        "#### `colour/blue.yaml`",
        "| `colour.shade` | `0.1` |  |",
    ]:
        assert line in lines, line
    assert lines.index("#### `colour/blue.yaml`") < lines.index("#### `colour/red.yaml`")
    long = next(ln for ln in lines if ln.startswith("| `long` |"))
    assert long.startswith("| `long` | `[aaaaaaaaaa, bbbbbbbbbb, ") and "…] (9 items)` |" in long
    assert "iiiiiiiiii" not in long
    assert "```text" in lines and text.count("@package") == 1  # the directive is not shown as prose


def test_check_and_write(tiny_conf, tmp_path, capsys):
    out = tmp_path / "configuration.md"
    assert confref.main(["--conf-dir", str(tiny_conf), "--out", str(out), "--check"]) == 1
    assert "is missing" in capsys.readouterr().err
    assert confref.main(["--conf-dir", str(tiny_conf), "--out", str(out)]) == 0
    assert out.read_text(encoding="utf-8") == confref.reference_markdown(tiny_conf)
    assert confref.main(["--conf-dir", str(tiny_conf), "--out", str(out), "--check"]) == 0
    out.write_text(out.read_text(encoding="utf-8") + "edited by hand\n", encoding="utf-8")
    assert confref.main(["--conf-dir", str(tiny_conf), "--out", str(out), "--check"]) == 1
    err = capsys.readouterr().err.strip()
    assert "is stale" in err and "python -m tools.confref" in err and "\n" not in err
