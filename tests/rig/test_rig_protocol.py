"""Telemetry parsing, unit conversion, commands and rig config validation (no pty)."""

import json
import math

import pytest

from mfdesign.rig.config import Affine, ConfigError, RigConfig
from mfdesign.rig.protocol import LBF_TO_N, PSI_TO_PA, Command, TelemetryError, parse_telemetry

CFG = RigConfig()


def test_parse_converts_units_and_heights():
    s = parse_telemetry(b"12.500,10.0,1.0,80.0,90.0,0.8,1", CFG)
    assert s.rig_time_s == 12.5
    assert s.force_n == pytest.approx(10 * 4.4482216152605)
    assert s.pressure_pa == pytest.approx(6894.757293168)
    assert (s.left_mm, s.right_mm) == (40.0, 30.0)  # height = -tof + 120
    assert s.height_mm == 35.0 and not s.contact
    assert parse_telemetry("1,0,0,80,80,0,0\r", CFG).contact  # limit switch 0: touched


def test_dropout_gives_nan_and_other_sensor_is_used():
    s = parse_telemetry("1,0,0,8190,80,0,1", CFG)
    assert math.isnan(s.left_mm) and s.height_mm == 40.0
    s = parse_telemetry("1,0,0,400,400,0,1", CFG)  # 400 is already a dropout
    assert math.isnan(s.height_mm)


@pytest.mark.parametrize(
    "line, why",
    [
        ("1,2,3,4,5,6", "7 comma-separated"),
        ("1,2,3,4,5,6,1,8", "7 comma-separated"),
        ("1,2,x,4,5,6,1", "pressure_psi"),
        ("1,2,nan,4,5,6,1", "pressure_psi"),
        ("1,2,3,4,5,6,2", "limit_switch"),
        ("1,2,3,4,5,6,", "empty field"),
        ("1, 2,3,4,5,6,1", "whitespace"),
        ("-1,2,3,4,5,6,1", "time"),
        ("1,2,3,-4,5,6,1", "left_tof"),
        (b"1,2,3,4,\xff,6,1", "ASCII"),
    ],
)
def test_strict_parsing_rejects_with_reason(line, why):
    with pytest.raises(TelemetryError, match=why):
        parse_telemetry(line, CFG)


def test_command_characters():
    assert Command.PUMP_ON == "w" and Command.PUMP_OFF == "s"
    assert Command.VALVE_OPEN == "q" and Command.VALVE_CLOSE == "a"
    assert [c.value for c in (Command.LEFT_PUSH, Command.LEFT_PULL, Command.LEFT_STOP)] == list("uio")
    assert [c.value for c in (Command.RIGHT_PUSH, Command.RIGHT_PULL, Command.RIGHT_STOP)] == list("jkl")
    assert [c.value for c in (Command.BOTH_PUSH, Command.BOTH_STOP, Command.BOTH_PULL)] == list("yhn")
    assert (Command.RESET, Command.SENSORS_ON, Command.SENSORS_OFF) == ("m", "9", "0")
    assert LBF_TO_N == 4.4482216152605 and PSI_TO_PA == 6894.757293168


def test_affine_inverse():
    a = Affine(scale=-0.98, offset_mm=117.0)
    assert a.height_mm(a.tof(33.3)) == pytest.approx(33.3)


def test_config_toml_and_json(tmp_path):
    p = tmp_path / "rig.toml"
    p.write_text("telemetry_timeout_s = 0.5\npush_lowers_plate = false\n[tof_left]\nscale = -1.02\noffset_mm = 118\n")
    c = RigConfig.load(p)
    assert c.telemetry_timeout_s == 0.5 and c.tof_left == Affine(-1.02, 118.0) and not c.push_lowers_plate
    j = tmp_path / "rig.json"
    j.write_text(json.dumps(c.to_dict()))
    assert RigConfig.load(j) == c


@pytest.mark.parametrize(
    "text, msg",
    [
        ("telemetry_timout_s = 1", "unknown key"),
        ("telemetry_timeout_s = -1", "positive"),
        ('telemetry_timeout_s = "1"', "must be a number"),
        ("[tof_left]\nscale = 0\noffset_mm = 1", "non-zero"),
        ("[tof_left]\nslope = 1", "scale and offset_mm"),
        ("height_min_mm = 80", "below height_max_mm"),
        ("port_baudrate = 115201", "standard rate"),
        ("push_lowers_plate = 1", "true or false"),
        ("telemetry_timeout_s = ", "not valid TOML"),
    ],
)
def test_config_errors_name_the_key(tmp_path, text, msg):
    p = tmp_path / "rig.toml"
    p.write_text(text)
    with pytest.raises(ConfigError, match=msg):
        RigConfig.load(p)


def test_config_missing_file_and_suffix(tmp_path):
    with pytest.raises(ConfigError, match="cannot read"):
        RigConfig.load(tmp_path / "nope.toml")
    (tmp_path / "rig.yaml").write_text("a: 1")
    with pytest.raises(ConfigError, match=".toml or .json"):
        RigConfig.load(tmp_path / "rig.yaml")


def test_connection_assembles_lines_split_across_reads_and_counts_bad_ones():
    """Bytes of one line arriving in pieces, long garbage without a newline, a stale time."""
    import os
    import time
    import tty

    from mfdesign.rig.protocol import RigConnection

    master, slave = os.openpty()
    tty.setraw(slave)
    try:
        conn = RigConnection(os.ttyname(slave), RigConfig(telemetry_timeout_s=5.0))
        try:
            assert os.read(master, 64) == b"s\nq\nh\n"  # safe state on connect
            os.write(master, b"\n1.000,1.0,0.5,80.0,8")
            time.sleep(0.05)
            os.write(master, b"0.0,0.0,1\n")
            os.write(master, b"x" * 300)  # no newline within 256 bytes
            time.sleep(0.05)
            os.write(master, b"\n0.500,1.0,0.5,80.0,80.0,0.0,1\n")  # time went backwards
            os.write(master, b"2.000,2.0,0.5,80.0,80.0,0.0,0\n")
            a, b = conn.next_sample(timeout=2), conn.next_sample(timeout=2)
            assert (a.rig_time_s, a.force_n) == (1.0, pytest.approx(LBF_TO_N)) and b.contact
            time.sleep(0.05)
            assert conn.bad_lines in (2, 3) and conn.good_lines == 2  # 3: overflow cut mid-read
        finally:
            conn.close()
        assert conn.ser.is_open is False
    finally:
        os.close(master)
        os.close(slave)
