"""ros2msg schema texts written by imufdi (concatenated with dependencies, as
``ros2 bag record`` stores them)."""

from __future__ import annotations

SEPARATOR = "=" * 80

IMU_SCHEMA_NAME = "sensor_msgs/msg/Imu"
MAG_SCHEMA_NAME = "sensor_msgs/msg/MagneticField"
STATUS_SCHEMA_NAME = "imufdi_msgs/msg/FdiStatus"
FAULT_EVENT_SCHEMA_NAME = "imufdi_msgs/msg/FaultEvent"
FDI_EVENT_SCHEMA_NAME = "imufdi_msgs/msg/FdiEvent"

_HEADER = """# Standard metadata for higher-level stamped data types.
# Used to communicate timestamped data in a particular coordinate frame.

# Two-integer timestamp that is expressed as seconds and nanoseconds.
builtin_interfaces/Time stamp

# Transform frame with which this data is associated.
string frame_id
"""

_TIME = """# This message communicates ROS Time, defined here:
# https://design.ros2.org/articles/clock_and_time.html

# The seconds component, valid over all int32 values.
int32 sec

# The nanoseconds component, valid in the range [0, 1e9).
uint32 nanosec
"""

_QUATERNION = """# This represents an orientation in free space in quaternion form.

float64 x 0
float64 y 0
float64 z 0
float64 w 1
"""

_VECTOR3 = """# This represents a vector in free space.

float64 x
float64 y
float64 z
"""

_IMU = """# This is a message to hold data from an IMU (Inertial Measurement Unit)
#
# Accelerations should be in m/s^2 (not in g's), and rotational velocity should be in rad/sec
#
# If the covariance of the measurement is known, it should be filled in (if all you know is the
# variance of each measurement, e.g. from the datasheet, just put those along the diagonal)
# A covariance matrix of all zeros will be interpreted as "covariance unknown", and to use the
# data a covariance will have to be assumed or gotten from some other source
#
# If you have no estimate for one of the data elements (e.g. your IMU doesn't produce an
# orientation estimate), please set element 0 of the associated covariance matrix to -1
# If you are interpreting this message, please check for a value of -1 in the first element of each
# covariance matrix, and disregard the associated estimate.

std_msgs/Header header

geometry_msgs/Quaternion orientation
float64[9] orientation_covariance # Row major about x, y, z axes

geometry_msgs/Vector3 angular_velocity
float64[9] angular_velocity_covariance # Row major about x, y, z axes

geometry_msgs/Vector3 linear_acceleration
float64[9] linear_acceleration_covariance # Row major x, y z
"""

_MAG = """# Measurement of the Magnetic Field vector at a specific location.
#
# If the covariance of the measurement is known, it should be filled in.
# If all you know is the variance of each measurement, e.g. from the datasheet,
# just put those along the diagonal.
# A covariance matrix of all zeros will be interpreted as "covariance unknown",
# and to use the data a covariance will have to be assumed or gotten from some
# other source.

std_msgs/Header header               # timestamp is the time the
                                     # field was measured
                                     # frame_id is the location and orientation
                                     # of the field measurement

geometry_msgs/Vector3 magnetic_field # x, y, and z components of the
                                     # field vector in Tesla
                                     # If your sensor does not output 3 axes,
                                     # put NaNs in the components not reported.

float64[9] magnetic_field_covariance # Row major about x, y, z axes
                                     # 0 is interpreted as variance unknown
"""

_STATUS = """# Per-sample output of an imufdi detector for one sensor type.
std_msgs/Header header            # stamp = the sample's time; frame_id = the array body frame
builtin_interfaces/Time decided   # when the decision on this sample became available
float64 statistic   # detection statistic
float64 threshold   # threshold it is compared to
bool alarm          # fault declared
int32 isolated      # index into the channel's sensor_ids; -1 none, -2 not isolable
float64 amplitude   # estimated fault amplitude (SI), NaN when none
float64[] scores    # per-sensor isolation scores
bool[] isolated_set # every sensor isolated at this sample (several simultaneous faults)
float64[] amplitudes  # estimated fault amplitude of every sensor (SI), NaN where none
"""


_FAULT_EVENT = """# Start or end of a fault injected by imufdi (ground truth, one message per mark).
# header.stamp: the time the fault starts or ends; header.frame_id is empty.
std_msgs/Header header

string event            # "start" or "end"
float64 t_s             # the same time, seconds after the log start
string fault_id         # unique within the log (f0, f1, ... unless the spec names one)
string model            # step, drift, noise, stuck, scale or spikes
string[] sensors        # faulted sensor ids, e.g. imu0.gyro.x
float64 at_s            # fault start, seconds after the log start
float64 until_s         # fault end (exclusive), seconds after the log start; NaN: end of log
string[] param_names    # model parameters, SI units (e.g. amp in rad/s)
float64[] param_values
string spec             # the fault as the user wrote it
"""

_FDI_EVENT = """# Start or end of an alarm of an imufdi detector, for one sensor type, or an episode.
# header.stamp: the sample at which the alarm starts or ends; header.frame_id is empty.
std_msgs/Header header

string detector         # e.g. glt
string sensor_type      # gyro, accel or mag
string event            # "alarm_start" or "alarm_end"
string isolated         # sensor id isolated at that sample; empty when none
bool isolable           # false when isolation is impossible (too few sensors per axis)
float64 amplitude       # estimated fault amplitude (SI); NaN when none
float64 statistic       # detection statistic at that sample

# An explained alarm episode (event "episode"; header.stamp = decision time of its last
# alarm); empty strings and NaN for alarm_start/alarm_end. docs/episodes.md.
string fault_class      # step, drift, noise, scale, spikes, stuck, clipping, dropout or none;
                        # "" when unexplained
string size_name        # amp, rate (per second), factor, value or duration (s)
float64 size            # SI units of the sensor type; NaN when none
float64 size_low        # confidence interval of size (level in detail)
float64 size_high
string detail           # the whole explanation as JSON: times, sensors, every fit, evidence
int64 start_ns          # episode: its first and last alarmed sample (log time, ns; as
int64 end_ns            # start_ns and end_ns in detail); 0 for alarm_start/alarm_end
"""


def _concat(main: str, deps: list[tuple[str, str]]) -> bytes:
    parts = [main]
    for name, text in deps:
        parts.append(f"{SEPARATOR}\nMSG: {name}\n{text}")
    return "\n".join(parts).encode("utf-8")


IMU_SCHEMA = _concat(
    _IMU,
    [
        ("std_msgs/Header", _HEADER),
        ("builtin_interfaces/Time", _TIME),
        ("geometry_msgs/Quaternion", _QUATERNION),
        ("geometry_msgs/Vector3", _VECTOR3),
    ],
)
MAG_SCHEMA = _concat(
    _MAG,
    [
        ("std_msgs/Header", _HEADER),
        ("builtin_interfaces/Time", _TIME),
        ("geometry_msgs/Vector3", _VECTOR3),
    ],
)
STATUS_SCHEMA = _concat(_STATUS, [("std_msgs/Header", _HEADER), ("builtin_interfaces/Time", _TIME)])
FAULT_EVENT_SCHEMA = _concat(
    _FAULT_EVENT, [("std_msgs/Header", _HEADER), ("builtin_interfaces/Time", _TIME)]
)
FDI_EVENT_SCHEMA = _concat(
    _FDI_EVENT, [("std_msgs/Header", _HEADER), ("builtin_interfaces/Time", _TIME)]
)


#: package and name prefix of the per-channel named-scores types (``SensorScores`` and 8
#: hex digits of the CRC-32 of the sensor ids: one type per set of sensors)
SCORES_SCHEMA_PREFIX = "imufdi_msgs/msg/SensorScores"


def scores_schema(fields: list[str]) -> tuple[str, bytes]:
    """Name and ros2msg text of the named-scores message of one status channel: the
    header, then one ``float64`` per sensor, named after it (``imu0_gyro_x``), so that
    Foxglove and PlotJuggler show every sensor's score under its name."""
    import zlib

    digest = zlib.crc32("\n".join(fields).encode("utf-8"))
    main = (
        "# Per-sensor isolation scores of an imufdi status channel (the same values as its\n"
        "# scores[], in sensor_ids order), one field per sensor, named after it.\n"
        "std_msgs/Header header  # stamp = the sample's time; frame_id = the array body frame\n"
        + "".join(f"float64 {name}\n" for name in fields)
    )
    text = _concat(main, [("std_msgs/Header", _HEADER), ("builtin_interfaces/Time", _TIME)])
    return f"{SCORES_SCHEMA_PREFIX}{digest:08X}", text
