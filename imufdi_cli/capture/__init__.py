"""Raw serial captures of IMU arrays: frame layouts, parsing, encoding, ingest to MCAP.

>>> layout = load_layout("mpu6500-array", gyro_fs="500dps", accel_fs="4g")
>>> blocks, stats = parse_capture("board.cap", layout)
>>> for block in blocks: ...            # ImuBlock, SI units; stats complete afterwards
"""

from imufdi_cli.capture.binary import BinaryFrameParser, find_sync
from imufdi_cli.capture.checksum import (
    CHECKSUM_KINDS,
    CRC_CATALOGUE,
    CrcModel,
    compute_checksums,
    crc,
    find_crc,
)
from imufdi_cli.capture.encode import (
    CaptureEncoder,
    Corruption,
    EncodedCapture,
    encode_capture,
    encode_frames,
)
from imufdi_cli.capture.layout import (
    BUILTIN_LAYOUTS,
    ChecksumSpec,
    CsvMapping,
    HeaderField,
    Layout,
    RecordField,
)
from imufdi_cli.capture.layouts import layout_from_dict, load_layout, mpu6500_array
from imufdi_cli.capture.parse import (
    DEFAULT_CHUNK_SIZE,
    DEFAULT_MCAP_CHUNK_SIZE,
    ingest,
    parse_capture,
)
from imufdi_cli.capture.stats import IngestStats

__all__ = [
    "BUILTIN_LAYOUTS",
    "CHECKSUM_KINDS",
    "CRC_CATALOGUE",
    "DEFAULT_CHUNK_SIZE",
    "DEFAULT_MCAP_CHUNK_SIZE",
    "BinaryFrameParser",
    "CaptureEncoder",
    "ChecksumSpec",
    "Corruption",
    "CrcModel",
    "CsvMapping",
    "EncodedCapture",
    "HeaderField",
    "IngestStats",
    "Layout",
    "RecordField",
    "compute_checksums",
    "crc",
    "encode_capture",
    "encode_frames",
    "find_crc",
    "find_sync",
    "ingest",
    "layout_from_dict",
    "load_layout",
    "mpu6500_array",
    "parse_capture",
]
