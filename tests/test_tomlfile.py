"""imufdi_cli.tomlfile: one mapping of tomllib's failures to the caller's error."""

from __future__ import annotations

import pytest

from imufdi_cli.errors import ArrayConfigError, LayoutError
from imufdi_cli.tomlfile import parse_toml


def test_parses_text_and_utf8_bytes_alike():
    doc = 'name = "café"\n[imu]\nrate = 100\n'
    assert parse_toml(doc, "a.toml", LayoutError) == {"name": "café", "imu": {"rate": 100}}
    assert parse_toml(doc.encode("utf-8"), "a.toml", LayoutError) == parse_toml(
        doc, "a.toml", LayoutError
    )


@pytest.mark.parametrize(
    ("raw", "detail"),
    [
        (b"rate = = 1\n", "not valid TOML (Invalid"),
        (b"name = '\xff'\n", "not valid TOML ('utf-8' codec"),
        ("x = " + "[" * 100_000 + "]" * 100_000 + "\n", "nested too deeply"),
    ],
)
def test_failures_raise_the_callers_error_naming_the_file(raw, detail):
    with pytest.raises(ArrayConfigError, match=r"^board\.toml: ") as info:
        parse_toml(raw, "board.toml", ArrayConfigError)
    assert detail in str(info.value)
