"""ArrayConfig per-IMU calibration (M, b) and range: parsing, validation, round trips."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.testing import assert_allclose

from imufdi_cli.array import ArrayConfig, TriadCalibration
from imufdi_cli.errors import ArrayConfigError

TOML = """
rate_hz = 62.5
[range]
gyro = "2000deg/s"
accel = "16g"

[[imu]]
gyro_matrix = [[1.01, 0.002, 0], [0, 0.99, 0], [0, 0, 1]]
gyro_bias = ["0.5deg/s", 0, 0]
accel_bias = [0.1, -0.2, 0.3]

[[imu]]
rotation = [[0, -1, 0], [-1, 0, 0], [0, 0, -1]]
"""


def _load(tmp_path, text):
    path = tmp_path / "a.toml"
    path.write_text(text)
    return ArrayConfig.load(path)


def test_calibration_parsed_with_units_and_defaults(tmp_path):
    array = _load(tmp_path, TOML)
    gyro = array.imus[0].calibration_of("gyro")
    assert_allclose(gyro.bias, [np.radians(0.5), 0, 0])
    assert_allclose(gyro.matrix[0], [1.01, 0.002, 0])
    accel = array.imus[0].calibration_of("accel")
    assert_allclose(accel.matrix, np.eye(3))  # bias only: M defaults to identity
    assert array.imus[1].calibration_of("gyro").is_identity
    assert array.calibrated
    assert_allclose(array.range["gyro"], np.radians(2000))
    assert_allclose(array.range["accel"], 16 * 9.80665)


def test_toml_and_json_round_trip(tmp_path):
    array = _load(tmp_path, TOML)
    assert ArrayConfig.from_json(array.to_json()) == array
    again = tmp_path / "b.toml"
    array.save(again)
    assert ArrayConfig.load(again) == array


def test_apply_and_undo_are_inverse():
    rng = np.random.default_rng(0)
    cal = TriadCalibration(
        matrix=np.eye(3) + 0.01 * rng.standard_normal((3, 3)), bias=rng.standard_normal(3)
    )
    raw = rng.standard_normal((50, 3))
    assert_allclose(cal.apply(raw), (raw - cal.bias) @ cal.matrix.T)
    assert_allclose(cal.undo(cal.apply(raw)), raw, atol=1e-12)


@pytest.mark.parametrize(
    ("line", "fragment"),
    [
        (
            "accel_matrix = [[1, 0, 0], [0, 1, 0], [0, 0, 0]]",
            "imu1 accel calibration: matrix is singular",
        ),
        (
            "gyro_matrix = [[1, 1, 0], [1, 1, 0], [0, 0, 1]]",
            "imu1 gyro calibration: matrix is singular",
        ),
        ("gyro_bias = [nan, 0, 0]", "imu1 gyro calibration: matrix and bias must be finite"),
        ("accel_matrix = [[inf, 0, 0], [0, 1, 0], [0, 0, 1]]", "imu1 accel calibration"),
        ("accel_bias = [1, 2]", "imu1 accel calibration: bias must be [x, y, z]"),
        ("accel_matrix = [[1, 0], [0, 1]]", "imu1 accel calibration: matrix must be 3x3"),
        ('gyro_bias = ["1m", 0, 0]', "imu1 gyro calibration"),
    ],
)
def test_bad_calibration_names_the_imu(tmp_path, line, fragment):
    with pytest.raises(ArrayConfigError, match=fragment.replace("[", r"\[").replace("]", r"\]")):
        _load(tmp_path, TOML + line + "\n")


def test_bad_range(tmp_path):
    with pytest.raises(ArrayConfigError, match=r"range\.gyro"):
        _load(tmp_path, 'range = {gyro = "-1deg/s"}\n[[imu]]\n')
    with pytest.raises(ArrayConfigError, match=r"range\.speed"):
        _load(tmp_path, 'range = {speed = "1m/s"}\n[[imu]]\n')


def test_with_calibration_and_check_matches(tmp_path):
    array = _load(tmp_path, TOML)
    plain = array.with_calibration(None)
    assert not plain.calibrated
    assert plain.with_range({"gyro": 1.0}).range["gyro"] == array.range["gyro"]  # kept
    with pytest.raises(ArrayConfigError, match="2 IMUs but the log has 3"):
        array.check_matches(ArrayConfig.co_aligned(3))


def test_per_imu_noise_parsed_round_trip_and_checked(tmp_path):
    text = TOML.replace(
        "accel_bias = [0.1, -0.2, 0.3]",
        'accel_bias = [0.1, -0.2, 0.3]\ngyro_noise = ["0.2deg/s", "0.25deg/s", "0.3deg/s"]',
    )
    array = _load(tmp_path, text)
    assert_allclose(array.imus[0].noise["gyro"], np.radians([0.2, 0.25, 0.3]))
    assert array.per_sensor_noise
    # imu1 has no gyro_noise and there is no array-wide noise.gyro: no per-sensor sigmas
    assert array.sensor_noise("gyro") is None
    filled = array.with_sensor_noise([{"gyro": np.full(3, 0.01)}, {"gyro": np.full(3, 0.02)}])
    assert_allclose(filled.sensor_noise("gyro"), [0.01] * 3 + [0.02] * 3)
    assert ArrayConfig.from_json(filled.to_json()) == filled
    again = tmp_path / "noise.toml"
    filled.save(again)
    assert ArrayConfig.load(again) == filled
    with pytest.raises(ArrayConfigError, match=r"imu0 gyro_noise.*positive"):
        _load(tmp_path, text.replace('"0.2deg/s"', "-1"))
    with pytest.raises(ArrayConfigError, match=r"imu0 gyro_noise.*\[x, y, z\]"):
        _load(tmp_path, text.replace('"0.2deg/s", ', ""))


def test_per_imu_noise_spread_parsed_round_trip_and_checked(tmp_path):
    text = TOML.replace(
        "accel_bias = [0.1, -0.2, 0.3]",
        "accel_bias = [0.1, -0.2, 0.3]\ngyro_noise_spread = [1.0, 1.5, 2.25]",
    )
    array = _load(tmp_path, text)
    assert_allclose(array.imus[0].noise_spread["gyro"], [1.0, 1.5, 2.25])
    # imu1 has none: no per-sensor spread for the type
    assert array.sensor_noise_spread("gyro") is None
    filled = array.with_noise_spread([{"gyro": np.full(3, 1.5)}, {"gyro": [1.0, 2.0, 3.0]}])
    assert_allclose(filled.sensor_noise_spread("gyro"), [1.5] * 3 + [1.0, 2.0, 3.0])
    assert ArrayConfig.from_json(filled.to_json()) == filled
    again = tmp_path / "spread.toml"
    filled.save(again)
    assert ArrayConfig.load(again) == filled
    with pytest.raises(ArrayConfigError, match=r"imu0 gyro_noise_spread.*>= 1"):
        _load(tmp_path, text.replace("[1.0, 1.5, 2.25]", "[0.9, 1.5, 2.25]"))
    with pytest.raises(ArrayConfigError, match=r"imu0 gyro_noise_spread.*\[x, y, z\]"):
        _load(tmp_path, text.replace("[1.0, 1.5, 2.25]", "[1.5, 2.25]"))
    with pytest.raises(ArrayConfigError, match=r"spread"):
        array.with_noise_spread([{"gyro": [1.0, 0.5, 1.0]}, {}])


def test_sensor_index_is_built_once_per_array_read_only_and_follows_the_axes() -> None:
    """The index arrays are made once per array and sensor type (every block's ``select``
    reads them) and cannot be changed through a caller; an unknown type is refused every
    time; an array derived from another gets its own."""
    from dataclasses import replace

    from imufdi_cli.array import ImuSpec

    array = ArrayConfig(
        imus=(
            ImuSpec(axes={"gyro": ("x", "z"), "accel": ("x", "y", "z"), "mag": ()}),
            ImuSpec(axes={"gyro": ("y",), "accel": (), "mag": ()}),
        )
    )
    imu_idx, axis_idx = array.sensor_index("gyro")
    assert imu_idx.tolist() == [0, 0, 1] and axis_idx.tolist() == [0, 2, 1]
    assert array.sensor_index("gyro")[0] is imu_idx
    assert array.sensor_ids("gyro") == ["imu0.gyro.x", "imu0.gyro.z", "imu1.gyro.y"]
    assert array.sensor_index("mag")[0].size == 0
    with pytest.raises(ValueError, match="read-only"):
        imu_idx[0] = 1
    for _ in range(2):
        with pytest.raises(ArrayConfigError, match="unknown sensor type 'baro'"):
            array.sensor_index("baro")
    triads = np.arange(2 * 2 * 3, dtype=float).reshape(2, 2, 3)
    np.testing.assert_array_equal(array.select(triads, "gyro"), triads[:, [0, 0, 1], [0, 2, 1]])
    # an array derived by dataclasses.replace builds its own index from its own IMUs
    swapped = replace(array, imus=array.imus[::-1])
    assert swapped.sensor_index("gyro")[0].tolist() == [0, 1, 1]
    assert swapped.sensor_index("gyro")[1].tolist() == [1, 0, 2]
    assert array.sensor_index("gyro")[1].tolist() == [0, 2, 1]
