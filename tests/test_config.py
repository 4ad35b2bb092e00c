"""companion.config: TOML -> frozen, validated dataclasses; errors name the file and the key."""
from __future__ import annotations

import dataclasses

import pytest

from companion.config import (Config, ConfigError, FilterConfig, example_config_toml, load_config,
                              loads_config)
from companion.nav.engine import EngineConfig
from companion.nav.filter import ProcessNoise


def test_empty_file_gives_defaults(tmp_path):
    p = tmp_path / "c.toml"
    p.write_text("")
    cfg = load_config(p)
    assert cfg.mavlink.connection == "udpin:127.0.0.1:14550"
    assert cfg.mavlink.source_component == 191 and cfg.mavlink.imu_rate_hz == 200.0
    assert cfg.corrections.source == "none" and cfg.output.mode == "vision"
    assert cfg.source_path == str(p)
    with pytest.raises(dataclasses.FrozenInstanceError):
        cfg.mavlink.imu_rate_hz = 5


def test_example_round_trips_and_is_complete(tmp_path):
    text = example_config_toml()
    p = tmp_path / "example.toml"
    p.write_text(text)
    cfg = load_config(p)
    assert dataclasses.replace(cfg, source_path="") == Config()
    for section in ("[mavlink]", "[gnss]", "[gnss.serial]", "[corrections]", "[corrections.ntrip]",
                    "[corrections.serial]", "[corrections.mqtt]", "[corrections.file]", "[output]",
                    "[filter]", "[log]", "[telemetry]"):
        assert section in text
    assert "# base_position_ecef_m = ...   (optional, not set)" in text


def test_full_file_parses_with_types():
    cfg = loads_config("""
[mavlink]
connection = "/dev/ttyACM0,921600"
imu_message = "HIGHRES_IMU"
imu_rate_hz = 400
[gnss]
source = "serial"
lever_arm_b_m = [0.1, 0, -0.25]
[gnss.serial]
port = "/dev/ttyAMA0"
baud = 460800
[corrections]
source = "ntrip"
forward_to_autopilot = true
base_position_ecef_m = [-3551876.8287, 3887786.8598, 3586946.3873]
[corrections.ntrip]
host = "caster.example"
mountpoint = "VRS"
version = 1
gga_interval_s = 10
[output]
mode = "gps_input"
rate_hz = 5
[filter]
use_tdcp = false
gyro_arw_rad_per_sqrt_s = 1e-4
[telemetry]
enabled = true
topic_prefix = "uav7"
""", "full.toml")
    assert cfg.mavlink.imu_rate_hz == 400.0 and isinstance(cfg.mavlink.imu_rate_hz, float)
    assert cfg.gnss.lever_arm_b_m == (0.1, 0.0, -0.25) and cfg.gnss.serial.baud == 460800
    assert cfg.corrections.base_position_ecef_m[0] == pytest.approx(-3551876.8287)
    assert cfg.corrections.ntrip.version == 1 and cfg.output.mode == "gps_input"
    ec = cfg.engine_config()
    assert isinstance(ec, EngineConfig) and isinstance(ec.noise, ProcessNoise)
    assert ec.use_tdcp is False and ec.noise.gyro_arw_rad_per_sqrt_s == 1e-4
    assert ec.lever_arm_b_m == (0.1, 0.0, -0.25)


@pytest.mark.parametrize("text, needle", [
    ("[mavlink]\nimu_rate_hz = 'fast'\n", "x.toml: mavlink.imu_rate_hz: expected a number"),
    ("[mavlink]\nimu_message = 'IMU9'\n", "mavlink.imu_message: must be one of auto, HIGHRES_IMU"),
    ("[mavlnk]\n", "unknown key mavlnk"),
    ("[corrections.ntrip]\nverison = 2\n", "unknown key corrections.ntrip.verison"),
    ("[output]\nrate_hz = 100\n", "output.rate_hz: must be <= 50.0"),
    ("[gnss]\nlever_arm_b_m = [0, 1]\n", "gnss.lever_arm_b_m: expected an array of 3 numbers"),
    ("[corrections]\nsource = 'ntrip'\n", "corrections.ntrip.mountpoint: required"),
    ("[corrections]\nsource = 'file'\n", "corrections.file.path: required"),
    ("[log]\nenabled = 1\n", "log.enabled: expected true or false"),
    ("[mavlink]\nsource_system = 300\n", "mavlink.source_system: must be <= 255"),
    ("[filter]\nsigma_phase_m = 0\n", "filter.sigma_phase_m: must be > 0"),
    ("mavlink = 3\n", "mavlink: expected a table"),
    ("[mavlink\n", "x.toml: not valid TOML"),
])
def test_errors_name_file_and_key(text, needle):
    with pytest.raises(ConfigError) as e:
        loads_config(text, "x.toml")
    assert needle in str(e.value)


def test_missing_file(tmp_path):
    with pytest.raises(ConfigError, match="configuration file not found"):
        load_config(tmp_path / "nope.toml")


def test_filter_fields_exist_in_engine_config():
    engine_fields = {f.name for f in dataclasses.fields(EngineConfig)}
    noise_fields = {f.name for f in dataclasses.fields(ProcessNoise)}
    for f in dataclasses.fields(FilterConfig):
        assert f.name in engine_fields | noise_fields, f.name
