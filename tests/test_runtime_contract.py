"""The C runtime and the Python export agree on what is written once on each side (the
kind codes, the limits and the activation codes were typed by hand in several places with no
cross-check): tb_runtime.h and tb_registry.def against thermbench/export (fileformat.Kind,
encoding.LIMITS, encoding.ACTIVATION_CODES, target.KIND_CODES), read from the sources as text."""

from __future__ import annotations

import re

from thermbench.export import encoding, target
from thermbench.export.fileformat import DATA_KINDS, ENVELOPE_KIND, FAULTS_KIND, Kind
from thermbench.export.runtime import embedded_dir

HEADER = (embedded_dir() / "include" / "tb_runtime.h").read_text()
REGISTRY = (embedded_dir() / "src" / "tb_registry.def").read_text()

#: encoding.LIMITS names -> the header's TB_MAX_* (ar_terms and effects live in the kinds' own files)
LIMIT_MACROS = {"sensors": "SENSORS", "poly": "POLY", "table": "TABLE", "support": "SUPPORT", "layers": "LAYERS",
                "width": "WIDTH", "gru_hidden": "GRU_HIDDEN", "lags": "LAGS", "nodes": "NODES", "ar_order": "AR_ORDER",
                "levels": "LEVELS", "conditions": "CONDITIONS", "window_samples": "WINDOW",
                "lumped_nodes": "LUMPED_NODES", "lag_taus": "LAG_TAUS"}  # fmt: skip


def test_the_kind_codes_are_one_list_on_both_sides():
    enum = {m[1]: int(m[2]) for m in re.finditer(r"\bTB_KIND_(\w+)\s*=\s*(\d+)", HEADER)}
    top = enum.pop("MAX")
    assert enum == {k.name: int(k) for k in Kind} and top == max(int(k) for k in Kind)
    registered = re.findall(r"^TB_KIND\(TB_KIND_(\w+),\s*(\w+)\)", REGISTRY, re.M)
    assert sorted(registered) == sorted((k.name, k.name.lower()) for k in Kind)
    for _, name in registered:  # each kind's table in its own file
        assert f"const tbi_kind tbi_kind_{name} = " in (embedded_dir() / "src" / f"tb_kind_{name}.c").read_text()
    assert target.KIND_CODES == {int(k): k.name.lower() for k in Kind}
    # the envelope file (tb_guard_open) and the faults file (tb_faults_open): kind codes of their own,
    # outside the models'
    for code, name in DATA_KINDS.items():
        m = re.search(rf"#define TB_KIND_{name} (\d+)u", HEADER)
        assert m and int(m[1]) == code and code not in {int(k) for k in Kind}
    assert DATA_KINDS == {ENVELOPE_KIND: "ENVELOPE", FAULTS_KIND: "FAULTS"}


def test_the_limits_are_the_headers():
    macros = {m[1]: int(m[2]) for m in re.finditer(r"#define TB_MAX_(\w+) (\d+)u", HEADER)}
    assert {k: encoding.LIMITS[k] for k in LIMIT_MACROS} == {k: macros[v] for k, v in LIMIT_MACROS.items()}
    assert encoding.MAX_FILTER_STEPS == macros["FILTER_STEPS"]
    ar = (embedded_dir() / "src" / "tb_kind_ar.c").read_text()
    assert f"nu > {encoding.LIMITS['ar_terms']}" in ar  # the AR's operating terms
    physics = (embedded_dir() / "src" / "tb_physics.h").read_text()
    assert f"#define TBI_MAX_EFFECTS {encoding.LIMITS['effects']}u" in physics


def test_the_activation_codes_are_the_mlp_kinds():
    mlp = (embedded_dir() / "src" / "tb_kind_mlp.c").read_text()
    names = re.search(r"enum \{ ACT_TANH = 1, ([^}]*)\}", mlp)
    order = ["tanh", *[n.strip()[4:].lower() for n in names[1].split(",") if n.strip()]]
    assert encoding.ACTIVATION_CODES == {name: i + 1 for i, name in enumerate(order)}
