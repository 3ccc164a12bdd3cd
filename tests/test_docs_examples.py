"""The worked examples of docs/extending.md run as written.

Each ``## `` section of the page is one example. Its fenced blocks (indented ones
dedented) are taken in order, in an empty temporary working directory: a block whose
first line is ``# file: PATH`` (``// file: PATH`` in C) is written to PATH (what the reader
saves), every other ```python block is executed, all in one namespace per section; other
fences (bash, yaml without a file line, diff) are not run. The asserts check what the
examples compute, not just that they ran.
"""

from __future__ import annotations

import os
import re
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

DOC = Path(__file__).resolve().parents[1] / "docs" / "extending.md"
FENCE = re.compile(r"^([ \t]*)```([\w+-]*)[^\n]*\n(.*?)^\1```[ \t]*$", re.S | re.M)
FILE_LINE = re.compile(r"^(?:#|//)\s*file:\s*(\S+)\s*$")
FAMILY = "How to add a model family"
EFFECT = "How to add an effect"


def sections(text: str) -> dict[str, list[tuple[str, str]]]:
    """``## `` heading -> its fenced blocks ``(language, code)`` in order."""
    out: dict[str, list[tuple[str, str]]] = {}
    parts = re.split(r"^## (.+)$", text, flags=re.M)
    for title, body in zip(parts[1::2], parts[2::2]):
        out[title.strip()] = [(m.group(2), textwrap.dedent(m.group(3))) for m in FENCE.finditer(body)]
    return out


def run_section(title: str, tmp_path: Path, monkeypatch) -> dict:
    """Write the section's files and execute its Python blocks in ``tmp_path``; return the namespace."""
    blocks = sections(DOC.read_text(encoding="utf-8"))[title]
    assert blocks, f"docs/extending.md: no code blocks under '## {title}'"
    monkeypatch.chdir(tmp_path)
    monkeypatch.syspath_prepend(str(tmp_path))
    ns: dict = {"__name__": "docs_example"}
    for i, (lang, code) in enumerate(blocks):
        first = code.splitlines()[0] if code.strip() else ""
        m = FILE_LINE.match(first)
        if m:
            path = tmp_path / m.group(1)
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(code, encoding="utf-8")
        elif lang == "python":
            exec(compile(code, f"{DOC.name} [{title}] block {i + 1}", "exec"), ns)
    return ns


@pytest.fixture
def clean_imports():
    """Forget the modules the examples create and any effect they register; the runtime copy
    the effect example builds with (THERMBENCH_EMBEDDED_DIR) is the test's only."""
    from thermbench.sim import EFFECTS

    before_env = os.environ.pop("THERMBENCH_EMBEDDED_DIR", None)
    before_modules = set(sys.modules)
    before_effects = dict(EFFECTS)
    yield
    os.environ.pop("THERMBENCH_EMBEDDED_DIR", None)
    if before_env is not None:
        os.environ["THERMBENCH_EMBEDDED_DIR"] = before_env
    for name in set(sys.modules) - before_modules:
        if name in ("ridge_family", "heat_effects"):
            del sys.modules[name]
    EFFECTS.clear()
    EFFECTS.update(before_effects)


def test_the_page_has_both_examples():
    found = sections(DOC.read_text(encoding="utf-8"))
    for title in (FAMILY, EFFECT):
        langs = [lang for lang, _ in found[title]]
        assert "python" in langs, title


def test_model_family_example(tmp_path, monkeypatch, clean_imports):
    ns = run_section(FAMILY, tmp_path, monkeypatch)
    from thermbench.export import Kind

    ds, held_out, fitted = ns["ds"], ns["held_out"], ns["fitted"]
    assert type(fitted).__name__ == "RidgeSensors" and type(ns["model"]).__name__ == "RidgeSensors"
    assert ns["model"].get_params()["alpha"] == 1.0  # built from conf/model/ridge.yaml
    # fits and predicts finite values of the right shape
    pred = np.asarray(ns["pred_um"])
    assert pred.shape == (len(ds.errors_run(held_out)),)
    assert np.isfinite(pred).all()
    assert ns["table"].error_um.shape[1] == 6 and np.isfinite(ns["table"].error_um).all()
    assert fitted.required_inputs().sensors == tuple(ns["screw_side"])
    # on the held-out run it beats predicting zero (no compensation) by far
    rmse = ns["heldout_rmse_um"]
    assert set(rmse) == {"ridge, all sensors", "ridge, screw-side sensors", "mlr_seed002"}
    assert rmse["ridge, screw-side sensors"] < 0.25 * ns["zero_rmse_um"]
    assert rmse["ridge, all sensors"] < ns["zero_rmse_um"]
    # export: through its export_encoding, as the existing MLR_CURVE kind, checked in the C runtime
    man = ns["manifest"]
    assert man["kind"] == Kind.MLR_CURVE.name and man["parity"]["runs"] == [held_out]
    assert ns["parity_um"] <= man["parity"]["tolerance_um"] == 0.01
    assert (tmp_path / "exports" / "ridge" / "manifest.json").exists()


def test_effect_example(tmp_path, monkeypatch, clean_imports):
    ns = run_section(EFFECT, tmp_path, monkeypatch)
    # the new effect changes the error: the field directly, and the simulated readings
    assert ns["field_change_um"] > 3.0
    assert ns["error_change_um"].max() > 3.0
    assert ns["ds"].metadata.simulation["effects"]["nearby_heat_source"]["power_W"] == 2.0
    # the physics model recovers its power and predicts the held-out run better with it
    assert abs(ns["identified_power_W"] - 2.0) < 0.3
    heldout = ns["heldout"]
    assert heldout["core + nearby_heat_source"] < 0.5 * heldout["core"]
    assert ns["export_refusal"].startswith("model: effect 'nearby_heat_source' has no C implementation;")
    # its C file, registered in a copy of the runtime: exported, and C matches Python on the held-out run
    man = ns["nearby_manifest"]
    assert man["kind"] == "PHYSICS" and man["parity"]["runs"] == ["feed6000"]
    assert man["parity"]["model"]["max_abs_diff_um"] < 0.01
    c_file = (tmp_path / "embedded" / "src" / "tb_fx_nearby_heat_source.c").read_text()
    assert c_file.startswith("// file: tb_fx_nearby_heat_source.c") and ".code = 8" in c_file
