"""Packaging for a board (issue 15): what the service imports, the extras, the command line's basics.

The start-up path must not pay for scipy.stats (about 1 s and 40 MB) or matplotlib; a configuration
error must come before numpy, scipy or pymavlink are even imported; optional dependencies are
imported lazily and, when missing, name the extra that installs them.
"""
from __future__ import annotations

import ast
import json
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
CORE = {"numpy", "scipy", "pymavlink", "serial", "pyrtcm", "pynmeagps", "anycrc"}   # import names of the core dependencies
OPTIONAL = {"matplotlib": "plot", "aiomqtt": "mqtt", "pyubx2": "sitl", "georinex": "test"}


def _modules_after(code: str) -> set[str]:
    """Top-level package names in sys.modules after running ``code`` in a fresh interpreter."""
    probe = code + "\nimport json, sys\nprint(json.dumps(sorted(sys.modules)))\n"
    r = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=120, cwd=REPO)
    assert r.returncode == 0, r.stderr
    return set(json.loads(r.stdout.strip().splitlines()[-1]))


def test_service_import_pulls_neither_scipy_stats_nor_matplotlib():
    mods = _modules_after("import companion.service")
    assert "companion.service" in mods
    heavy = sorted(m for m in mods if m == "scipy.stats" or m.startswith(("scipy.stats.", "matplotlib")))
    assert not heavy, f"import companion.service imports {heavy[:5]}"


def test_config_check_imports_no_numpy_scipy_or_pymavlink(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text("[output]\nmax_sigma_h_m = 1e300\n")
    mods = _modules_after(f"from companion.cli import main\nrc = main(['config', 'check', {str(bad)!r}])\n"
                          "assert rc == 2, rc")
    heavy = sorted(m for m in mods if m.split(".")[0] in {"numpy", "scipy", "pymavlink", "matplotlib", "pyrtcm"})
    assert not heavy, f"companion config check imports {heavy[:5]}"


def test_version_matches_the_installed_metadata():
    from importlib.metadata import version

    import companion
    r = subprocess.run([sys.executable, "-m", "companion", "--version"], capture_output=True, text=True,
                       timeout=60, cwd=REPO)
    assert r.returncode == 0 and r.stdout == f"companion {companion.__version__}\n"
    assert version("companion") == companion.__version__


def _pyproject() -> dict:
    return tomllib.loads((REPO / "pyproject.toml").read_text())


def _names(reqs) -> set[str]:
    import re
    return {re.split(r"[<>=!~\[; ]", r, maxsplit=1)[0].lower() for r in reqs}


def test_core_dependencies_are_what_the_service_needs_and_extras_cover_the_rest():
    proj = _pyproject()["project"]
    core = _names(proj["dependencies"])
    assert core == {"numpy", "scipy", "pymavlink", "pyserial", "pyrtcm", "pynmeagps", "anycrc"}
    extras = {k: _names(v) for k, v in proj["optional-dependencies"].items()}
    assert extras["plot"] == {"matplotlib"} and extras["mqtt"] == {"aiomqtt"}
    assert {"pyubx2", "matplotlib"} <= extras["sitl"]
    # scripts/test.sh installs [test] only: it must hold every other extra and the test tools
    for name, pkgs in extras.items():
        assert pkgs <= extras["test"], f"[test] lacks {sorted(pkgs - extras['test'])} of [{name}]"
    assert {"pytest", "pytest-timeout", "georinex"} <= extras["test"]


def _module_level_imports(path: Path):
    """(line, top-level package) of every import executed when the module is imported, except
    inside a ``try`` that falls back when it fails (an optional accelerator such as anycrc)."""
    tree = ast.parse(path.read_text(), str(path))

    def falls_back(node) -> bool:
        return isinstance(node, ast.Try) and any(
            h.type is None or (isinstance(h.type, ast.Name) and h.type.id in ("ImportError", "ModuleNotFoundError",
                                                                             "Exception"))
            for h in node.handlers)

    def walk(nodes):
        for node in nodes:
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)) or falls_back(node):
                continue
            if isinstance(node, ast.Import):
                for a in node.names:
                    yield node.lineno, a.name.split(".")[0]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                yield node.lineno, node.module.split(".")[0]
            if isinstance(node, ast.ClassDef):
                yield from walk(node.body)
            elif hasattr(node, "body") and not isinstance(node, ast.ClassDef):
                for field in ("body", "orelse", "finalbody", "handlers"):
                    yield from walk(getattr(node, field, []) or [])
    yield from walk(tree.body)


def test_companion_imports_optional_dependencies_only_lazily():
    stdlib = set(sys.stdlib_module_names)
    offenders = []
    for path in sorted((REPO / "companion").rglob("*.py")):
        for line, top in _module_level_imports(path):
            if top in stdlib or top in ("companion", "__future__") or top in CORE:
                continue
            why = (f"use companion.extras.require, extra [{OPTIONAL[top]}]" if top in OPTIONAL
                   else "not a core dependency")
            offenders.append(f"{path.relative_to(REPO)}:{line}: import {top} at module level ({why})")
    assert not offenders, "\n".join(offenders)


def test_a_missing_extra_is_named(monkeypatch, capsys, tmp_path):
    from companion.cli import main
    from companion.extras import MissingExtra, pyplot, require
    monkeypatch.setitem(sys.modules, "matplotlib", None)      # as if matplotlib were not installed
    with pytest.raises(MissingExtra, match=r"replay --plot needs matplotlib, which is not installed: "
                                           r"pip install 'companion\[plot\]'"):
        pyplot("replay --plot")
    assert main(["allan", str(tmp_path / "static.csv"), "--plot", str(tmp_path / "a.png")]) == 2
    assert "pip install 'companion[plot]'" in capsys.readouterr().err
    monkeypatch.setitem(sys.modules, "aiomqtt", None)
    with pytest.raises(ImportError, match=r"companion\[mqtt\]"):
        require("aiomqtt", "mqtt", "MQTT telemetry")


def test_every_companion_module_imports_with_the_core_dependencies_alone():
    """With the optional packages hidden, every module imports, or (io.mqtt) says which extra it needs."""
    hidden = sorted(OPTIONAL) + ["xarray", "pandas"]
    probe = f"""
import importlib, json, pkgutil, sys
for m in {hidden!r}:
    sys.modules[m] = None                      # import of m now fails as if it were not installed
import companion
from companion.extras import MissingExtra
res = {{}}
for info in pkgutil.walk_packages(companion.__path__, "companion."):
    if info.name.endswith("__main__"):
        continue                               # runs the command line when imported
    try:
        importlib.import_module(info.name)
        res[info.name] = "ok"
    except MissingExtra as exc:
        res[info.name] = "extra: " + str(exc)
    except Exception as exc:
        res[info.name] = f"{{type(exc).__name__}}: {{exc}}"
print(json.dumps(res))
"""
    r = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=300, cwd=REPO)
    assert r.returncode == 0, r.stderr
    res = json.loads(r.stdout.strip().splitlines()[-1])
    assert "companion.service" in res and "companion.replay" in res
    assert res.get("companion.io.mqtt", "").startswith("extra: ") and "companion[mqtt]" in res["companion.io.mqtt"]
    broken = {k: v for k, v in res.items() if v != "ok" and k != "companion.io.mqtt"}
    assert not broken, broken


def test_run_refuses_to_start_without_the_extra_its_config_needs(monkeypatch, capsys, tmp_path):
    from companion.cli import main
    monkeypatch.setitem(sys.modules, "aiomqtt", None)
    monkeypatch.setitem(sys.modules, "companion.service", None)   # were the check skipped: fail, not fly
    p = tmp_path / "c.toml"
    p.write_text("[corrections]\nsource = 'mqtt'\n")
    assert main(["run", "--config", str(p)]) == 2
    err = capsys.readouterr().err
    assert f"{p}: corrections.source = 'mqtt' needs aiomqtt" in err and "pip install 'companion[mqtt]'" in err
