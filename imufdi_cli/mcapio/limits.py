"""Limits of the MCAP reader: how much a file may make it allocate or expand.

Every size an MCAP file declares (a record length, a chunk's uncompressed size, a fixed
array's element count in a schema) is checked against these limits *before* anything is
allocated, so a corrupt or hostile file costs at most a bounded amount of memory and time.
The defaults are far above what real logs use (``ros2 bag record`` writes chunks of about
1 MiB, the ``mcap`` tools 4 MiB); they can be raised per reader
(``McapSource(path, limits=ReaderLimits(...))``) or for every command through environment
variables:

=============================== ============ ==================================================
variable                        default      what it bounds
=============================== ============ ==================================================
``IMUFDI_MAX_CHUNK_BYTES``      64 MiB       a chunk's declared uncompressed size
``IMUFDI_MAX_RECORD_BYTES``     128 MiB      a record held in memory (chunk, message, schema,
                                             channel, metadata); attachments and unknown
                                             records are skipped without being held
``IMUFDI_MAX_SCHEMA_FIELDS``    100000       fields of a ros2msg type once nested types and
                                             fixed arrays of strings/messages are expanded
``IMUFDI_MAX_SCHEMA_DEPTH``     32           nesting depth of message types
=============================== ============ ==================================================
"""

from __future__ import annotations

import os
from dataclasses import dataclass

from imufdi_cli.errors import UsageError

MIB = 1 << 20


def _env_int(name: str, default: int) -> int:
    text = os.environ.get(name)
    if text is None or not text.strip():
        return default
    try:
        value = int(text.strip().replace("_", ""))
    except ValueError:
        raise UsageError(f"{name} must be a positive integer, got {text!r}") from None
    if value < 1:
        raise UsageError(f"{name} must be a positive integer, got {text!r}")
    return value


@dataclass(frozen=True)
class ReaderLimits:
    """Caps the reader applies to sizes declared by a file (see the module docstring).

    Attributes
    ----------
    max_chunk_bytes : int
        Largest declared uncompressed size of a chunk, bytes.
    max_record_bytes : int
        Largest record read into memory, bytes.
    max_schema_fields : int
        Largest number of fields of an expanded ros2msg type.
    max_schema_depth : int
        Deepest nesting of message types.
    """

    max_chunk_bytes: int = 64 * MIB
    max_record_bytes: int = 128 * MIB
    max_schema_fields: int = 100_000
    max_schema_depth: int = 32

    @classmethod
    def from_env(cls) -> ReaderLimits:
        """Defaults, overridden by the ``IMUFDI_MAX_*`` environment variables."""
        base = cls()
        return cls(
            max_chunk_bytes=_env_int("IMUFDI_MAX_CHUNK_BYTES", base.max_chunk_bytes),
            max_record_bytes=_env_int("IMUFDI_MAX_RECORD_BYTES", base.max_record_bytes),
            max_schema_fields=_env_int("IMUFDI_MAX_SCHEMA_FIELDS", base.max_schema_fields),
            max_schema_depth=_env_int("IMUFDI_MAX_SCHEMA_DEPTH", base.max_schema_depth),
        )
