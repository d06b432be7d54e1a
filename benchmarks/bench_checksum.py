"""Frame checksums: imufdi's table-driven numpy CRCs against CRC libraries.

The parser verifies the checksums of every candidate frame of a chunk at once
(``imufdi_cli.capture.checksum``: one numpy step per byte column, two bytes per step for
8- and 16-bit CRCs). A CRC library computes one frame per call, so a chunk costs one
Python call per frame. Measured here on F frames of L bytes (random bytes; the frames of
a 1 MiB parser chunk of the built-in 16-IMU layout are about 4400 x 234 bytes), in MB of
covered bytes per second:

- imufdi numpy, for catalogue CRCs of widths 8, 16, 32 and Fletcher-16;
- crcmod-plus (``crcmod.mkCrcFun``, C), anycrc (``anycrc.Model``, C) and fastcrc (Rust),
  each called once per frame, when installed (``pip install crcmod-plus anycrc fastcrc``);
- zlib.crc32 per frame (what imufdi uses for CRC-32/ISO-HDLC).

Ratios are against imufdi's numpy figure measured in the same run (> 1: the library is
faster). Prints the load average.

Usage: python benchmarks/bench_checksum.py [--frames 4400] [--lengths 234,104,30] [--repeat 5]
"""

from __future__ import annotations

import argparse
import os
import time
import zlib
from collections.abc import Callable

import numpy as np

from imufdi_cli.capture.checksum import crc, find_crc, fletcher16

MODELS = ("CRC-8/SMBUS", "CRC-16/XMODEM", "CRC-16/MODBUS", "CRC-32/ISCSI", "CRC-32/ISO-HDLC")
#: fastcrc's function per catalogue name (its catalogue is fixed)
FASTCRC = {
    "CRC-8/SMBUS": ("crc8", "smbus"),
    "CRC-16/XMODEM": ("crc16", "xmodem"),
    "CRC-16/MODBUS": ("crc16", "modbus"),
    "CRC-32/ISCSI": ("crc32", "iscsi"),
    "CRC-32/ISO-HDLC": ("crc32", "iso_hdlc"),
}


def best(fn: Callable[[], object], repeat: int) -> float:
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return min(times)


def per_frame(function: Callable[[bytes], int], data: np.ndarray) -> Callable[[], object]:
    flat = data.tobytes()
    length = data.shape[1]
    view = memoryview(flat)

    def run() -> object:
        return np.fromiter(
            (function(view[i : i + length]) for i in range(0, len(flat), length)),
            dtype=np.uint64,
            count=data.shape[0],
        )

    return run


def libraries(name: str) -> dict[str, Callable[[bytes], int]]:
    model = find_crc(name)
    assert model is not None
    out: dict[str, Callable[[bytes], int]] = {}
    try:
        import crcmod

        # crcmod's initCrc is the initial register xored with the final xor
        out["crcmod-plus"] = crcmod.mkCrcFun(
            (1 << model.width) | model.poly,
            initCrc=model.init ^ model.xorout,
            rev=model.refin,
            xorOut=model.xorout,
        )
    except ImportError:
        pass
    try:
        import anycrc

        engine = anycrc.CRC(
            width=model.width,
            poly=model.poly,
            init=model.init,
            refin=model.refin,
            refout=model.refout,
            xorout=model.xorout,
        )
        out["anycrc"] = engine.calc
    except ImportError:
        pass
    try:
        import fastcrc

        module, function = FASTCRC[name]
        out["fastcrc"] = getattr(getattr(fastcrc, module), function)
    except (ImportError, AttributeError):
        pass
    if name == "CRC-32/ISO-HDLC":
        out["zlib"] = zlib.crc32
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--frames", type=int, default=4400)
    parser.add_argument("--lengths", default="234,104,30")
    parser.add_argument("--repeat", type=int, default=5)
    args = parser.parse_args()
    print(f"load average before: {os.getloadavg()}")
    rng = np.random.default_rng(1)
    for length in (int(x) for x in args.lengths.split(",")):
        data = rng.integers(0, 256, (args.frames, length), np.uint8)
        megabytes = data.size / 1e6
        print(f"{args.frames} frames x {length} bytes")
        for name in MODELS:
            model = find_crc(name)
            assert model is not None
            ours = best(lambda m=model, d=data: crc(m, d), args.repeat)
            expected = crc(model, data)
            line = f"  {name:16s} imufdi numpy {megabytes / ours:7.1f} MB/s"
            for lib, function in libraries(name).items():
                run = per_frame(function, data)
                assert np.array_equal(run(), expected), lib
                seconds = best(run, args.repeat)
                line += f" | {lib} {megabytes / seconds:7.1f} MB/s ({ours / seconds:4.2f}x)"
            print(line)
        seconds = best(lambda d=data: fletcher16(d), args.repeat)
        print(f"  {'Fletcher-16':16s} imufdi numpy {megabytes / seconds:7.1f} MB/s")
    print(f"load average after: {os.getloadavg()}")


if __name__ == "__main__":
    main()
