"""TOML parsing with the project's errors: one place maps tomllib's failures to a one-line
message naming the file, for array configs, layouts, fault files and campaign specs."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

from imufdi_cli.errors import ImufdiError


def parse_toml(raw: bytes | str, where: str | Path, error: type[ImufdiError]) -> dict[str, Any]:
    """The TOML document ``raw`` (bytes are decoded as UTF-8) as a dict.

    Invalid UTF-8, a TOML syntax error, or arrays/tables nested deeper than tomllib's
    recursive parser can follow raise ``error`` with ``"<where>: not valid TOML (...)"``.
    """
    if sys.version_info >= (3, 11):  # imported here: its regexes cost start-up time
        import tomllib
    else:  # pragma: no cover
        import tomli as tomllib
    try:
        text = raw.decode("utf-8") if isinstance(raw, bytes) else raw
        return tomllib.loads(text)
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as err:
        raise error(f"{where}: not valid TOML ({err})") from err
    except RecursionError as err:  # tomllib parses nested arrays/tables recursively
        raise error(f"{where}: not valid TOML (arrays or tables nested too deeply)") from err
