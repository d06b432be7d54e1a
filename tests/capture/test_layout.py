import math

import pytest

from imufdi_cli.capture import layout_from_dict, load_layout, mpu6500_array
from imufdi_cli.capture.layout import accel_scale, gyro_scale
from imufdi_cli.errors import LayoutError

from .conftest import LAYOUTS


def test_builtin_byte_map():
    layout = mpu6500_array()
    assert layout.sync == b"\xaa\x55"
    assert [(f.name, f.offset, f.size) for f in layout.header] == [
        ("version", 2, 1),
        ("n_imus", 3, 1),
        ("counter", 4, 2),
        ("timestamp", 6, 4),
    ]
    assert [f.name for f in layout.record] == [
        "accel_x", "accel_y", "accel_z", "temperature", "gyro_x", "gyro_y", "gyro_z",
    ]  # fmt: skip
    assert layout.record_size == 14
    assert layout.frame_size(16) == 10 + 16 * 14 + 2
    assert layout.checksum.resolve(layout.frame_size(1)) == (2, 24, 24)


@pytest.mark.parametrize(
    ("fs", "lsb_per_dps"), [("250dps", 131.0), ("500dps", 65.5), ("1000dps", 32.8), ("2000", 16.4)]
)
def test_gyro_full_scales(fs, lsb_per_dps):
    assert gyro_scale(fs) == pytest.approx(math.radians(1.0) / lsb_per_dps)


@pytest.mark.parametrize(
    ("fs", "lsb_per_g"), [("2g", 16384), ("4g", 8192), ("8", 4096), ("16g", 2048)]
)
def test_accel_full_scales(fs, lsb_per_g):
    assert accel_scale(fs) == pytest.approx(9.80665 / lsb_per_g)


def test_toml_of_the_builtin_layout_is_the_builtin_layout():
    toml = load_layout(LAYOUTS / "mpu6500-array.toml")
    builtin = load_layout("mpu6500-array")
    assert toml.header == builtin.header
    assert toml.record == builtin.record
    assert toml.checksum == builtin.checksum
    assert toml.sync == builtin.sync


def test_example_layouts_load():
    layout = load_layout(LAYOUTS / "sync1-be-sum16.toml")
    assert layout.frame_size(4) == 85 and layout.sensor_types == ("gyro", "accel", "mag")
    assert load_layout(LAYOUTS / "logger-csv.toml").kind == "csv"


BASE = {
    "sync": "A5",
    "n_imus": 1,
    "gyro_fs": "500dps",
    "record": [{"name": f"gyro_{a}", "type": "i16"} for a in "xyz"],
}


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"sync": None}, "missing key 'sync'"),
        ({"sync": "XZ"}, "not hex"),
        ({"record": [{"name": "gyro_x", "type": "u12"}]}, "unknown field type 'u12'; valid: u8"),
        ({"record": [{"name": "gyro_q", "type": "i16"}]}, "valid: accel_x"),
        ({"record": [{"name": "gyro_x", "type": "i16"}]}, "needs all of gyro_x"),
        ({"checksum": {"kind": "crc9-foo"}}, "valid: none, sum8"),
        ({"checksum": {"kind": "crc9-foo"}}, "catalogue CRC: CRC-8/SMBUS"),
        ({"checksum": {"kind": "crc16-ccitt"}}, "names several CRCs .CRC-16/IBM-3740"),
        ({"checksum": {"kind": "crc"}}, "kind = 'crc' needs width and poly"),
        ({"checksum": {"kind": "crc", "width": 65, "poly": 7}}, "checksum.width: must be <= 64"),
        (
            {"checksum": {"kind": "crc", "width": 8, "poly": 0x107}},
            "0x107 does not fit in width = 8",
        ),
        ({"checksum": {"kind": "crc", "width": 8, "poly": "x7"}}, "'x7' is not an integer"),
        ({"checksum": {"kind": "crc", "width": 8, "poly": 7, "refin": 1}}, "refin: expected true"),
        ({"checksum": {"kind": "crc", "width": 8, "poly": 0}}, "poly: must not be 0"),
        ({"checksum": {"kind": "CRC-16/MODBUS", "poly": 7}}, "CRC parameters go with kind = 'crc'"),
        ({"checksum": {"kind": "sum8", "end": 40}}, "checksum.end = 40 is past the frame"),
        ({"checksum": {"kind": "sum8", "at": -30}}, "checksum.at = -30 is past the frame"),
        ({"checksum": {"kind": "sum8", "start": 0, "end": 3, "at": 1}}, "inside the bytes"),
        ({"gyro_fs": "300dps"}, "valid: 250dps, 500dps"),
        ({"endian": "middle"}, "valid: little, big"),
        ({"bogus": 1}, "unknown key 'bogus'"),
        ({"n_imus": None}, "n_imus"),
        ({"header": [{"type": "u16", "role": "clock"}]}, "valid: counter, timestamp"),
        ({"header": [{"type": "u16", "role": "timestamp", "tick": "1m"}]}, "tick"),
    ],
)
def test_bad_layouts_raise_one_line_layout_errors(change, message):
    data = {**BASE, **change}
    data = {k: v for k, v in data.items() if v is not None}
    with pytest.raises(LayoutError, match=message) as info:
        layout_from_dict(data, source="board.toml")
    assert "\n" not in str(info.value)
    assert str(info.value).startswith("board.toml")


def test_unknown_layout_name_lists_choices(tmp_path):
    with pytest.raises(LayoutError, match="valid: mpu6500-array, csv"):
        load_layout("mpu9250")
    bad = tmp_path / "bad.toml"
    bad.write_text("sync = [")
    with pytest.raises(LayoutError, match="not valid TOML"):
        load_layout(bad)
    with pytest.raises(LayoutError, match="cannot read layout"):
        load_layout(tmp_path / "missing.toml")


PAD = {"name": "pad", "type": "pad"}
GYRO = BASE["record"]


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"n_imus": 100_000_000}, "n_imus: must be <= 1024, got 100000000"),
        ({"n_imus": None, "max_imus": 10**9}, "max_imus: must be <= 1024"),
        ({"trailer_pad": 10**12}, "trailer_pad: must be <= 1048576"),
        ({"record": [*GYRO, PAD | {"size": 10**12}]}, r"record\[3\].size: must be <= 1048576"),
        ({"header": [PAD | {"size": 10**12}]}, r"header\[0\].size: must be <= 1048576"),
        ({"n_imus": 1024, "record": [*GYRO, PAD | {"size": 2000}]}, "n_imus: a frame of 1024"),
    ],
)
def test_sizes_are_bounded_before_anything_is_allocated(change, message):
    data = {**BASE, **change}
    if data.get("n_imus") is None:
        data.pop("n_imus")
        data["header"] = [{"type": "u8", "role": "imu_count"}]
    with pytest.raises(LayoutError, match=message) as info:
        layout_from_dict(data, source="board.toml")
    assert "\n" not in str(info.value)


def test_largest_allowed_frame_loads():
    # 1024 IMUs of 1018-byte records with the 1-byte sync: 1024 * 1018 + 1 < 1 MiB
    data = {**BASE, "n_imus": 1024, "record": [*GYRO, PAD | {"size": 1012}]}
    assert layout_from_dict(data).frame_size(1024) == 1024 * 1018 + 1


def test_deeply_nested_toml_is_a_layout_error(tmp_path):
    deep = tmp_path / "deep.toml"
    deep.write_text('sync = "AA"\nx = ' + "[" * 5000 + "]" * 5000 + "\n")
    with pytest.raises(LayoutError, match="nested too deeply") as info:
        load_layout(deep)
    assert "\n" not in str(info.value)


def test_checksum_kinds_catalogue_names_and_parameters():
    from imufdi_cli.capture.checksum import find_crc

    def spec(checksum):
        return layout_from_dict({**BASE, "checksum": checksum}).checksum

    modbus = spec({"kind": "crc-16/modbus"})
    assert modbus.kind == "CRC-16/MODBUS" and modbus.model == find_crc("CRC-16/MODBUS")
    assert modbus.size == 2
    given = spec({"kind": "crc", "width": 16, "poly": 0x8005, "init": "0xFFFF", "refin": True})
    assert (given.model.refout, given.model.xorout, given.size) == (True, 0, 2)
    assert spec({"kind": "CRC-24/OPENPGP"}).size == 3
    assert spec({"kind": "crc-64/xz"}).size == 8
    assert (spec({"kind": "fletcher16"}).size, spec({"kind": "ubx"}).size) == (2, 2)
    # the kinds of earlier layouts keep their meaning
    assert spec({"kind": "crc16-ccitt-false"}).model is None
    assert spec({"kind": "crc32"}).size == 4
