"""The layers of docs/architecture.md hold: import-linter's contract in pyproject.toml, which
counts imports inside functions and ``if TYPE_CHECKING:`` blocks (.ci/run runs it too)."""

from __future__ import annotations

import textwrap
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

cli = pytest.importorskip("importlinter.cli", reason="import-linter is a test extra")


def _lint(config: Path, monkeypatch: pytest.MonkeyPatch, path: Path) -> int:
    monkeypatch.syspath_prepend(str(path))
    return cli.lint_imports(config_filename=str(config), no_cache=True, no_logo=True)


def test_the_package_keeps_its_layers(monkeypatch, capsys) -> None:
    code = _lint(ROOT / "pyproject.toml", monkeypatch, ROOT)
    out = capsys.readouterr().out
    assert code == 0, out
    assert "BROKEN" not in out and "0 broken" in out


def test_an_import_inside_a_function_breaks_the_contract(tmp_path, monkeypatch, capsys) -> None:
    """The checker sees what a grep of module-level imports misses: a lower layer importing
    a higher one inside a function. (A package laid out as this one, two layers deep.)"""
    package = tmp_path / "probe_layers"
    package.mkdir()
    (package / "__init__.py").write_text("")
    (package / "high.py").write_text("from probe_layers import low\n")
    (package / "low.py").write_text(
        textwrap.dedent(
            """
            def late():
                from probe_layers.high import low as again  # the violation
                return again
            """
        )
    )
    config = tmp_path / "pyproject.toml"
    contract = (ROOT / "pyproject.toml").read_text(encoding="utf-8")
    assert 'containers = ["imufdi_cli"]' in contract  # the form copied here
    config.write_text(
        textwrap.dedent(
            """
            [tool.importlinter]
            root_package = "probe_layers"

            [[tool.importlinter.contracts]]
            name = "probe"
            type = "layers"
            containers = ["probe_layers"]
            layers = ["high", "low"]
            exhaustive = true
            """
        )
    )
    code = _lint(config, monkeypatch, tmp_path)
    out = capsys.readouterr().out
    assert code != 0
    assert "probe_layers.low is not allowed to import probe_layers.high" in out


def test_no_module_is_over_800_lines() -> None:
    """A module a maintainer can read whole: longer ones are split by concern."""
    lengths = {
        str(path.relative_to(ROOT)): len(path.read_text(encoding="utf-8").splitlines())
        for path in (ROOT / "imufdi_cli").rglob("*.py")
    }
    assert {path: n for path, n in lengths.items() if n > 800} == {}
