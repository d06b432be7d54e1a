"""Print the oldest versions ``pyproject.toml`` admits, as a pip constraints file.

Every requirement with a ``>=`` floor in ``[project] dependencies`` and in the optional
extras becomes ``name==floor`` (extras and markers dropped: a constraint only pins what is
installed), except the linters (ruff, mypy, import-linter), which CI runs at their newest. ``.ci/run``
installs the built wheel and the test requirements under these constraints in a fresh
virtual environment on the oldest Python admitted, and runs the test suite there::

    python tools/floors.py > floors.txt              # the constraints
    python tools/floors.py --python                  # the oldest Python admitted: 3.10
    python tools/floors.py --test                    # the test extra but the linters
    python3.10 -m venv old && old/bin/pip install -c floors.txt dist/*.whl $(python tools/floors.py --test)
"""

from __future__ import annotations

import re
import sys
from pathlib import Path

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

ROOT = Path(__file__).resolve().parents[1]
#: not pinned: CI lints with the newest releases (their floors say what the config needs)
UNPINNED = frozenset({"ruff", "mypy", "import-linter"})
_REQUIREMENT = re.compile(r"^\s*([A-Za-z0-9][A-Za-z0-9._-]*)\s*(\[[^\]]*\])?\s*([^;]*)")


def floors(pyproject: Path = ROOT / "pyproject.toml") -> list[str]:
    """``name==version`` for every floored requirement of the project and its extras, in
    the order they are declared (each name once)."""
    project = tomllib.loads(pyproject.read_text(encoding="utf-8"))["project"]
    requirements = list(project.get("dependencies", []))
    for extra in project.get("optional-dependencies", {}).values():
        requirements += extra
    pins: dict[str, str] = {}
    for requirement in requirements:
        match = _REQUIREMENT.match(requirement)
        if match is None:
            raise SystemExit(f"tools/floors.py: cannot read the requirement {requirement!r}")
        name, specifiers = match.group(1).lower(), match.group(3)
        floor = [s.strip()[2:].strip() for s in specifiers.split(",") if s.strip().startswith(">=")]
        if name in UNPINNED or not floor or name in pins:
            continue
        pins[name] = floor[0]
    return [f"{name}=={version}" for name, version in pins.items()]


def oldest_python(pyproject: Path = ROOT / "pyproject.toml") -> str:
    """The lowest Python version ``requires-python`` admits (``>=3.10`` -> ``3.10``)."""
    project = tomllib.loads(pyproject.read_text(encoding="utf-8"))["project"]
    match = re.search(r">=\s*([0-9]+\.[0-9]+)", project.get("requires-python", ""))
    if match is None:
        raise SystemExit("tools/floors.py: requires-python has no >= floor")
    return match.group(1)


def test_requirements(pyproject: Path = ROOT / "pyproject.toml") -> list[str]:
    """The ``test`` extra's requirements (as declared), the linters left out."""
    project = tomllib.loads(pyproject.read_text(encoding="utf-8"))["project"]
    out = []
    for requirement in project.get("optional-dependencies", {}).get("test", []):
        match = _REQUIREMENT.match(requirement)
        if match is not None and match.group(1).lower() not in UNPINNED:
            out.append(requirement)
    return out


if __name__ == "__main__":
    if sys.argv[1:] == ["--python"]:
        print(oldest_python())
    elif sys.argv[1:] == ["--test"]:
        print("\n".join(test_requirements()))
    elif sys.argv[1:]:
        raise SystemExit("usage: python tools/floors.py [--python | --test]")
    else:
        print("\n".join(floors()))
