"""rosbag2 directories (``metadata.yaml`` plus split ``.mcap`` files) read as one log.

``ros2 bag record`` writes a directory holding ``metadata.yaml`` and one or more MCAP files
(``<name>_0.mcap``, ``<name>_1.mcap``, ... when the bag is split by size or duration). A
:class:`BagDirSource` chains the files in the order ``metadata.yaml`` lists them, as one
:class:`~imufdi_cli.mcapio.source.McapSource`: channels of the same topic, encoding and
schema in different files become one channel; metadata records of all files are merged;
warnings name the file they come from. ``McapSource(path)`` returns a BagDirSource when
``path`` is such a directory (or its ``metadata.yaml``), so every command reads bags.

Only the ``relative_file_paths`` list, ``storage_identifier`` and ``compression_mode`` of
``metadata.yaml`` are read, with a small parser for the YAML that rosbag2 writes (block
or flow sequences of plain or quoted scalars), so no YAML library is needed.
"""

from __future__ import annotations

import errno
import os
import re
import stat
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path
from typing import IO, Any

import numpy as np

from imufdi_cli.errors import McapInputError
from imufdi_cli.mcapio.limits import ReaderLimits
from imufdi_cli.mcapio.records import ChannelInfo, MessageBatch
from imufdi_cli.mcapio.source import McapSource

METADATA_FILE = "metadata.yaml"


def is_bag_dir(path: str | os.PathLike[str]) -> bool:
    """``path`` is a directory holding ``metadata.yaml``, or that file itself."""
    p = Path(path)
    if p.name == METADATA_FILE and p.is_file():
        return True
    return p.is_dir() and (p / METADATA_FILE).is_file()


def _scalar(text: str) -> str:
    text = text.strip()
    if len(text) >= 2 and text[0] == text[-1] and text[0] in "'\"":
        inner = text[1:-1]
        return inner.replace("''", "'") if text[0] == "'" else inner.replace('\\"', '"')
    return text.split(" #", 1)[0].strip()


def _value(lines: list[str], key: str) -> tuple[str | None, list[str]]:
    """Inline value of ``key:`` and the items of a block sequence under it."""
    pattern = re.compile(rf"^(\s*){re.escape(key)}:(.*)$")
    for index, line in enumerate(lines):
        match = pattern.match(line)
        if match is None:
            continue
        indent = len(match.group(1))
        inline = match.group(2).strip()
        items: list[str] = []
        for following in lines[index + 1 :]:
            if not following.strip() or following.lstrip().startswith("#"):
                continue
            stripped = following.lstrip()
            depth = len(following) - len(stripped)
            if depth < indent or (depth == indent and not stripped.startswith("- ")):
                break
            if stripped.startswith("- ") and depth <= indent + 2:
                items.append(_scalar(stripped[2:]))
        return inline, items
    return None, []


def bag_files(path: str | os.PathLike[str]) -> list[Path]:
    """The MCAP files of a rosbag2 directory, in the order ``metadata.yaml`` lists them.

    Raises
    ------
    McapInputError
        Unreadable ``metadata.yaml``, a storage other than MCAP, whole-file compression, or a
        listed file that is missing.
    """
    directory = Path(path)
    if directory.name == METADATA_FILE:
        directory = directory.parent
    meta = directory / METADATA_FILE
    try:
        lines = meta.read_text(encoding="utf-8").splitlines()
    except (OSError, UnicodeDecodeError) as err:
        raise McapInputError(f"{directory}: cannot read {METADATA_FILE} ({err})") from err
    storage, _ = _value(lines, "storage_identifier")
    if storage is not None and _scalar(storage) not in ("mcap", ""):
        raise McapInputError(
            f"{directory}: rosbag2 storage {_scalar(storage)!r} is not supported; only mcap"
            " (convert with `ros2 bag convert`)"
        )
    mode, _ = _value(lines, "compression_mode")
    if mode is not None and _scalar(mode).upper() == "FILE":
        raise McapInputError(
            f"{directory}: whole-file compressed bags are not supported (compression_mode"
            " FILE); decompress the files or record with --compression-mode message"
        )
    inline, items = _value(lines, "relative_file_paths")
    if inline and inline.startswith("["):
        items = [_scalar(x) for x in inline.strip("[]").split(",") if x.strip()]
    if not items:
        raise McapInputError(f"{directory}: {METADATA_FILE} lists no relative_file_paths")
    files = []
    for item in items:
        file = directory / item
        if not file.is_file() and (directory / Path(item).name).is_file():
            file = directory / Path(item).name  # older rosbag2 lists "<bag dir>/<file>"
        if not file.is_file():
            raise McapInputError(
                f"{directory}: {item}, listed in {METADATA_FILE}, {_not_a_file(file)}"
            )
        files.append(file)
    return files


def _not_a_file(path: Path) -> str:
    """Why ``path`` cannot be read as a split file, in words (``is missing``, ``is a
    directory``, ``is a symlink loop``...)."""
    try:
        info = path.stat()
    except OSError as err:
        if not os.path.lexists(path):
            return "is missing"
        if err.errno == errno.ELOOP:
            return "is a symlink loop (Too many levels of symbolic links)"
        if err.errno == errno.ENOENT:  # a dangling symlink
            return f"is a symlink to {os.readlink(path)}, which is missing"
        return f"cannot be read ({err.strerror})"
    if stat.S_ISDIR(info.st_mode):
        return "is a directory, not an MCAP file"
    return "is not a regular file (a device, FIFO or socket)"


def _channel_key(channel: ChannelInfo) -> tuple[Any, ...]:
    schema = channel.schema
    return (
        channel.topic,
        channel.message_encoding,
        None if schema is None else (schema.name, schema.encoding, schema.data),
    )


class BagDirSource(McapSource):
    """A rosbag2 directory read as one :class:`McapSource` (module docstring).

    Channel and schema ids are those of the first file that has them; a channel (schema)
    of a later file whose id is taken by another one gets a free id.
    """

    def __init__(
        self,
        source: str | os.PathLike[str] | IO[bytes],
        *,
        strict: bool = False,
        validate_crcs: bool | None = None,
        limits: ReaderLimits | None = None,
        keep_raw_chunks: bool = False,
        read_ahead: bool | None = None,
    ) -> None:
        # keep_raw_chunks is accepted and ignored: the split files' channels are renumbered
        # into one set, so their chunks are never copied verbatim (raw_chunk gives None).
        if not isinstance(source, (str, os.PathLike)):
            raise McapInputError("a rosbag2 directory must be given as a path")
        self.strict = strict
        self.validate_crcs = validate_crcs is not False
        self.read_ahead = bool(read_ahead)  # None: each file decides (McapSource)
        self.limits = limits if limits is not None else ReaderLimits.from_env()
        directory = Path(source)
        if directory.name == METADATA_FILE:
            directory = directory.parent
        self.name = os.fspath(directory)
        self.channels: dict[int, ChannelInfo] = {}
        self.schemas = {}
        self.metadata: dict[str, dict[str, str]] = {}
        self.warnings: list[str] = []
        self.summary_channel_counts: dict[int, int] | None = {}
        self.summary_message_count: int | None = 0
        self.summary_time_range: tuple[int, int] | None = None
        self._owns = False
        self._pending_channels = {}
        self._seekable = False
        self._iterator: Iterator[MessageBatch] | None = None
        self._pushback: list[MessageBatch] = []
        self.files = bag_files(directory)
        self._parts: list[McapSource] = []
        self._maps: list[dict[int, int]] = []
        self._keys: dict[tuple[Any, ...], int] = {}
        self._schema_ids: dict[tuple[Any, ...], int] = {}
        try:
            for file in self.files:
                part = McapSource(
                    file,
                    strict=strict,
                    validate_crcs=validate_crcs,
                    limits=self.limits,
                    read_ahead=read_ahead,
                )
                self._parts.append(part)
                self._maps.append({})
                self.warnings.extend(f"{file.name}: {w}" for w in part.warnings)
                self._merge(len(self._parts) - 1)
                self.metadata.update(part.metadata)
                self._merge_summary(len(self._parts) - 1)
        except BaseException:
            self.close()
            raise

    def _merge(self, index: int) -> None:
        """Give the channels of file ``index`` known so far their ids in the merged log."""
        part, mapping = self._parts[index], self._maps[index]
        for cid, channel in sorted(part.channels.items()):
            if cid in mapping:
                continue
            key = _channel_key(channel)
            out = self._keys.get(key)
            if out is None:
                out = cid if cid not in self.channels else max(self.channels) + 1
                self._keys[key] = out
                schema = channel.schema
                if schema is not None:
                    schema_key = (schema.name, schema.encoding, schema.data)
                    sid = self._schema_ids.get(schema_key)
                    if sid is None:
                        sid = schema.id if schema.id not in self.schemas else max(self.schemas) + 1
                        self._schema_ids[schema_key] = sid
                        self.schemas[sid] = replace(schema, id=sid)
                    schema = self.schemas[sid]
                self.channels[out] = replace(channel, id=out, schema=schema)
            mapping[cid] = out

    def _merge_summary(self, index: int) -> None:
        part, mapping = self._parts[index], self._maps[index]
        if part.summary_channel_counts is None or self.summary_channel_counts is None:
            self.summary_channel_counts = None
            self.summary_message_count = None
            self.summary_time_range = None
            return
        for cid, count in part.summary_channel_counts.items():
            if cid in mapping:
                out = mapping[cid]
                self.summary_channel_counts[out] = self.summary_channel_counts.get(out, 0) + count
        if self.summary_message_count is not None and part.summary_message_count is not None:
            self.summary_message_count += part.summary_message_count
        if part.summary_time_range is not None:
            low, high = part.summary_time_range
            if self.summary_time_range is not None:
                low = min(low, self.summary_time_range[0])
                high = max(high, self.summary_time_range[1])
            self.summary_time_range = (low, high)

    def _read_batches(self) -> Iterator[MessageBatch]:
        for index, part in enumerate(self._parts):
            part.warnings = _Prefixed(self.warnings, self.files[index].name)
            for batch in part.batches():
                ids = np.unique(batch.channel_id).tolist()
                if any(c not in self._maps[index] for c in ids):
                    self._merge(index)
                self.metadata.update(part.metadata)
                mapping = self._maps[index]
                if any(mapping[c] != c for c in ids):
                    lut = np.arange(65536, dtype=np.uint16)
                    for c in ids:
                        lut[c] = mapping[c]
                    batch = replace(batch, channel_id=lut[batch.channel_id])
                yield batch
            self.metadata.update(part.metadata)
            part.close()

    def close(self) -> None:
        for part in getattr(self, "_parts", []):
            part.close()


class _Prefixed(list):  # type: ignore[type-arg]
    """A list that appends to another with a file name prefix (warnings of one split)."""

    def __init__(self, target: list[str], prefix: str) -> None:
        super().__init__()
        self._target = target
        self._prefix = prefix

    def append(self, item: str) -> None:  # type: ignore[override]
        super().append(item)
        self._target.append(f"{self._prefix}: {item}")
