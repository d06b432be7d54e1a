"""The bulk MCAP writer.

:class:`McapWriter` builds Message records for many messages at once with numpy (one
structured header array, one payload copy), so writing cost does not involve per-message
Python work. Fixed-size records built by the caller (:meth:`McapWriter.add_records`) go
into chunks without further copies; records a :class:`RecordSource` can build
(:meth:`McapWriter.add_record_source`, used by the IMU writer) are built straight into the
chunk buffer on a worker thread. Each chunk is assembled, checksummed, compressed and
given its MessageIndex records on worker threads (numpy copies, zstandard, lz4 and the
CRC-32 release the GIL) while the caller goes on, and written in order, so the output is
the same bytes as a serial write.

Modules by concern, each importing only modules listed before it (no import cycles):

- :mod:`~imufdi_cli.mcapio.writer.parts`: the record sources callers queue
  (:class:`RecordSource`, :class:`TemplatedSource`) and the parts a chunk is made of;
- :mod:`~imufdi_cli.mcapio.writer.index`: MessageIndex records, ChunkIndex entries, the
  summary section and the Footer;
- :mod:`~imufdi_cli.mcapio.writer.chunks`: chunk building on worker threads (per-thread
  buffers, template-primed rows) and ``COMPRESS_THREADS``, ``MAX_CHUNKS_IN_FLIGHT``, read
  at call time (patch them there);
- :mod:`~imufdi_cli.mcapio.writer.output`, :mod:`~imufdi_cli.mcapio.writer.messages`,
  :mod:`~imufdi_cli.mcapio.writer.mcap_writer`: :class:`McapWriter`, assembled from one
  class per concern: ``McapWriter(_ChunkQueue(_Output))`` (output stream and temporary
  file; queued messages and chunks in flight; Header, Schema, Channel, Metadata records and
  the end of the file).
"""

from __future__ import annotations

from imufdi_cli.mcapio.writer.index import message_index_records
from imufdi_cli.mcapio.writer.mcap_writer import McapWriter
from imufdi_cli.mcapio.writer.parts import RecordSource, TemplatedSource

__all__ = ["McapWriter", "RecordSource", "TemplatedSource", "message_index_records"]


def __getattr__(name: str) -> object:
    """``COMPRESS_THREADS`` and ``MAX_CHUNKS_IN_FLIGHT``, read from
    :mod:`~imufdi_cli.mcapio.writer.chunks` (never copied here, so that patching them
    there takes effect)."""
    if name in ("COMPRESS_THREADS", "MAX_CHUNKS_IN_FLIGHT"):
        from imufdi_cli.mcapio.writer import chunks

        return getattr(chunks, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
