"""``make test`` and ``make target-test`` install the system packages they need (tools/sysdeps.sh,
tools/system-packages.txt). dpkg, apt-get, sudo and id are stand-ins on PATH here: each logs its
call; the stand-in dpkg says installed for the packages listed in a file the test writes."""

from __future__ import annotations

import os
import re
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
LIST = ROOT / "tools" / "system-packages.txt"

# a make of our own, not a sub-make of the `make test` that may be running this suite
CLEAN_ENV = {k: v for k, v in os.environ.items() if k not in ("MAKEFLAGS", "MAKELEVEL", "MFLAGS", "MAKEOVERRIDES")}

STANDINS = {
    # dpkg -s PKG: "installed" when PKG is a line of $TB_INSTALLED
    "dpkg": 'echo "dpkg $*" >> "$TB_LOG"; [ "$1" = -s ] || exit 1\n'
            'if grep -qx "$2" "$TB_INSTALLED"; then printf "Package: %s\\nStatus: install ok installed\\n" "$2"; '
            'else echo "dpkg-query: package \'$2\' is not installed" >&2; exit 1; fi',
    "apt-get": 'echo "apt-get $*" >> "$TB_LOG"',
    # sudo -n CMD...: works when $TB_SUDO is yes (then runs CMD), else refuses as sudo does without a password
    "sudo": 'echo "sudo $*" >> "$TB_LOG"; [ "$TB_SUDO" = yes ] || { echo "sudo: a password is required" >&2; exit 1; }\n'
            '[ "$1" = -n ] && shift; exec "$@"',
    "id": '[ "$1" = -u ] && echo "$TB_UID"',
}


def rows() -> list[tuple[str, str]]:
    """(package, make target) of the list, read here with a regex, not with the script's awk."""
    out = []
    for line in LIST.read_text(encoding="utf-8").splitlines():
        m = re.match(r"^([a-z0-9][a-z0-9+.-]+)\s+(test|target-test)\s+\S+", line)
        if m:
            out.append((m.group(1), m.group(2)))
    return out


@pytest.fixture
def standins(tmp_path):
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    for name, body in STANDINS.items():
        (bin_dir / name).write_text("#!/bin/sh\n" + body + "\n")
        (bin_dir / name).chmod(0o755)
    log, installed = tmp_path / "calls.log", tmp_path / "installed.txt"
    log.write_text("")

    def run(installed_pkgs, uid=0, sudo=False, target="test", via_make=True, list_file=None):
        installed.write_text("".join(p + "\n" for p in installed_pkgs))
        env = {**CLEAN_ENV, "PATH": f"{bin_dir}:{os.environ['PATH']}", "TB_LOG": str(log),
               "TB_INSTALLED": str(installed), "TB_UID": str(uid), "TB_SUDO": "yes" if sudo else "no"}
        lst = str(list_file or LIST)
        cmd = (["make", "-s", "--no-print-directory", "-C", str(ROOT), f"sysdeps-{target}", f"SYSDEPS_LIST={lst}"]
               if via_make else ["sh", str(ROOT / "tools" / "sysdeps.sh"), target, lst])
        p = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=60)
        calls = [ln for ln in log.read_text().splitlines() if not ln.startswith("dpkg ")]
        log.write_text("")
        return p, calls

    return run


@pytest.fixture
def fake_list(tmp_path):
    """A list whose probes are never found on this machine, so only the stand-in dpkg decides."""
    f = tmp_path / "packages.txt"
    f.write_text("# a comment\n"
                 "tb-fake-alpha  test    tb-no-such-command-a   first\n"
                 "tb-fake-beta   test    /nonexistent/tb/*/beta  second\n"
                 "tb-fake-gamma  test    -                       third\n"
                 "tb-fake-delta  target-test  tb-no-such-command-d  for the target\n")
    return f


def test_all_installed_runs_no_apt(standins, fake_list):
    p, calls = standins(["tb-fake-alpha", "tb-fake-beta", "tb-fake-gamma"], list_file=fake_list)
    assert p.returncode == 0, p.stderr
    assert calls == [] and p.stdout == "" and p.stderr == ""


def test_missing_as_root_installs_exactly_the_missing(standins, fake_list):
    p, calls = standins(["tb-fake-beta"], uid=0, list_file=fake_list)
    assert p.returncode == 0, p.stderr
    installs = [c for c in calls if " install " in f" {c} "]
    assert installs == ["apt-get install -y -q --no-install-recommends tb-fake-alpha tb-fake-gamma"]
    assert calls == ["apt-get update -q", installs[0]]  # no sudo as root


def test_missing_with_passwordless_sudo_goes_through_sudo(standins, fake_list):
    p, calls = standins([], uid=1000, sudo=True, list_file=fake_list, target="target-test")
    assert p.returncode == 0, p.stderr
    assert calls[0] == "sudo -n true"
    assert "sudo -n env DEBIAN_FRONTEND=noninteractive apt-get install -y -q --no-install-recommends tb-fake-delta" in calls
    assert calls[-1] == "apt-get install -y -q --no-install-recommends tb-fake-delta"


def test_missing_not_root_no_sudo_says_one_line_and_runs_nothing(standins, fake_list):
    p, calls = standins(["tb-fake-alpha"], uid=1000, sudo=False, list_file=fake_list, via_make=False)
    assert p.returncode == 2
    lines = p.stderr.splitlines()
    assert lines == ["make test needs system packages that are not installed: tb-fake-beta tb-fake-gamma; "
                     "run: sudo apt-get install --no-install-recommends tb-fake-beta tb-fake-gamma"]
    assert p.stdout == ""
    assert [c for c in calls if c.startswith("apt-get")] == []


def test_make_test_stops_before_anything_else(standins, fake_list, tmp_path):
    """`make test` runs the check first: with a package missing and no way to install it, no venv is
    made, no pip or npm runs."""
    installed = tmp_path / "installed.txt"
    installed.write_text("")
    venv = tmp_path / "never-made-venv"
    env = {**CLEAN_ENV, "PATH": f"{tmp_path / 'bin'}:{os.environ['PATH']}", "TB_LOG": str(tmp_path / "calls.log"),
           "TB_INSTALLED": str(installed), "TB_UID": "1000", "TB_SUDO": "no"}
    p = subprocess.run(["make", "--no-print-directory", "-C", str(ROOT), "test", f"SYSDEPS_LIST={fake_list}",
                        f"VENV={venv}"], env=env, capture_output=True, text=True, timeout=60)
    assert p.returncode == 2
    ours = [ln for ln in p.stderr.splitlines() if not re.match(r"make(\[\d+\])?: \*\*\* ", ln)]
    assert len(ours) == 1 and ours[0].startswith("make test needs system packages that are not installed: tb-fake-alpha")
    assert not venv.exists() and "pip" not in p.stdout and "npm" not in p.stdout


def test_the_real_list_is_what_the_readme_prints():
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    block = re.search(r"<!-- system-packages -->(.*?)<!-- /system-packages -->", readme, re.S)
    assert block, "README.md has no system-packages table"
    printed = re.findall(r"^\| `([^`]+)` \| `make (test|target-test)` \|", block.group(1), re.M)
    listed = rows()
    assert printed == listed
    # the packages the suite's own failure messages name are in the list
    names = {p for p, _ in rows()}
    assert {"linuxcnc-uspace", "postgresql", "nodejs", "npm", "gcc-arm-none-eabi", "libnewlib-arm-none-eabi",
            "qemu-system-arm"} <= names


def test_ci_installs_nothing_by_itself():
    ci = (ROOT / ".ci" / "run").read_text(encoding="utf-8")
    assert "apt-get install" not in ci and "make test" in ci and "make target-test" in ci
