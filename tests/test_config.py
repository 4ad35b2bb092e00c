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
    from companion.config import FILTER_SERVICE_FIELDS
    for f in dataclasses.fields(FilterConfig):
        assert f.name in engine_fields | noise_fields | FILTER_SERVICE_FIELDS, f.name


# ---------------------------------------------------------------------------------------------
# range checks on every numeric key (issue 14): absurd, non-finite and negative values are refused

def _leaf_fields(cls=Config, prefix=""):
    """(dotted key, field, type) of every leaf key of the configuration."""
    import typing
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        if f.metadata.get("internal"):
            continue
        tp = hints[f.name]
        if isinstance(tp, type) and dataclasses.is_dataclass(tp):
            yield from _leaf_fields(tp, f"{prefix}{f.name}.")
        else:
            yield prefix + f.name, f, tp


def _numeric_keys():
    return [(k, tp) for k, f, tp in _leaf_fields() if tp in (int, float)]


def _vector_keys():
    return [k for k, f, tp in _leaf_fields() if "tuple[float" in str(tp)]


def _toml_for(key: str, value: str) -> str:
    section, _, name = key.rpartition(".")
    return f"[{section}]\n{name} = {value}\n"


def test_every_numeric_key_has_a_finite_range_or_choices():
    for key, f, tp in _leaf_fields():
        if tp in (int, float) or "tuple[float" in str(tp):
            md = f.metadata
            assert md.get("choices") or (md.get("min") is not None and md.get("max") is not None), key
            if md.get("max") is not None:
                assert abs(md["max"]) < 1e13, key


@pytest.mark.parametrize("key, tp", _numeric_keys())
def test_absurd_numbers_are_refused_naming_the_key(key, tp):
    for value in ("1000000000000000000000000000000" if tp is int else "1e300",
                  "-1000000000000000000000000000000" if tp is int else "-1e300"):
        with pytest.raises(ConfigError) as e:
            loads_config(_toml_for(key, value), "x.toml")
        assert f"x.toml: {key}: must be" in str(e.value)
    if tp is float:
        for value in ("nan", "inf", "-inf"):
            with pytest.raises(ConfigError, match=f"x.toml: {key}: must be a finite number"):
                loads_config(_toml_for(key, value), "x.toml")


# times that are offsets, not intervals: either sign is meaningful (a clock that lags or leads)
SIGNED_TIME_KEYS = {"filter.imu_time_offset_s"}


@pytest.mark.parametrize("key", [k for k, tp in _numeric_keys() if k.endswith(("_hz", "_bps", "_s"))
                                 and k not in SIGNED_TIME_KEYS])
def test_negative_rates_and_intervals_are_refused(key):
    with pytest.raises(ConfigError, match=f"{key}: must be >"):
        loads_config(_toml_for(key, "-1.0"), "x.toml")


@pytest.mark.parametrize("key", sorted(SIGNED_TIME_KEYS))
def test_signed_time_offsets_accept_either_sign(key):
    section, name = key.split(".")
    for value in (-0.265, 0.08):
        assert getattr(getattr(loads_config(_toml_for(key, repr(value)), "x.toml"), section), name) == value


@pytest.mark.parametrize("key", _vector_keys())
def test_vector_elements_are_range_checked(key):
    with pytest.raises(ConfigError, match=rf"x.toml: {key}\[1\]: must be <="):
        loads_config(_toml_for(key, "[0.0, 1e300, 0.0]"), "x.toml")
    with pytest.raises(ConfigError, match=rf"{key}\[2\]: must be a finite number"):
        loads_config(_toml_for(key, "[0.0, 0.0, nan]"), "x.toml")


@pytest.mark.parametrize("text, needle", [
    ("[log]\nfsync_interval_s = 1e300\n", "x.toml: log.fsync_interval_s: must be <= 60.0, got 1e+300"),
    ("[output]\nmax_sigma_h_m = 1e300\n", "x.toml: output.max_sigma_h_m: must be <= 100.0, got 1e+300"),
    ("[output]\nmax_sigma_h_m = 0\n", "output.max_sigma_h_m: must be > 0.0"),
    ("[mavlink]\nimu_rate_hz = -200\n", "mavlink.imu_rate_hz: must be >= 1.0, got -200.0"),
    ("[mavlink]\nimu_rate_hz = nan\n", "mavlink.imu_rate_hz: must be a finite number, got nan"),
    ("[corrections.ntrip]\nport = 0\n", "corrections.ntrip.port: must be >= 1, got 0"),
    ("[corrections.ntrip]\nport = 2101.0\n", "corrections.ntrip.port: expected an integer, got 2101.0"),
    ("[log]\nmax_bytes = 100\n", "log.max_bytes: must be >= 4096, got 100"),
    ("[corrections]\nbase_position_ecef_m = [1.0, 2.0, 3.0]\n",
     "corrections.base_position_ecef_m: length must be between 6300000.0 and 6450000.0 m, got 3.74166 m"),
    ("[gnss]\nmoving_baseline_b_m = [0.0, 0.0, 0.0]\n", "gnss.moving_baseline_b_m: length must be between 0.05"),
    ("[gnss]\nsource = 'serial'\n[corrections]\nsource = 'serial'\n[corrections.serial]\nport = '/dev/ttyUSB0'\n",
     "corrections.serial.port: '/dev/ttyUSB0' is also gnss.serial.port"),
    ("[mavlink]\nimu_rat_hz = 100\n", "unknown key mavlink.imu_rat_hz (did you mean mavlink.imu_rate_hz?)"),
    ("[filter]\nuse_tdcp = true\nuse_dopler = true\n", "unknown key filter.use_dopler (did you mean filter.use_doppler?)"),
])
def test_range_and_consistency_errors(text, needle):
    with pytest.raises(ConfigError) as e:
        loads_config(text, "x.toml")
    assert needle in str(e.value)


def test_values_in_range_are_accepted():
    cfg = loads_config("[corrections]\nbase_position_ecef_m = [-3976219.5, 3382372.6, 3652513.0]\n"
                       "[gnss]\nmoving_baseline_b_m = [0.5, 0.0, 0.0]\n[log]\nfsync_interval_s = 0\n"
                       "[filter]\ngate_probability = 1.0\n")
    assert cfg.gnss.moving_baseline_b_m == (0.5, 0.0, 0.0) and cfg.log.fsync_interval_s == 0.0


def test_a_directory_or_binary_file_is_a_clear_error(tmp_path):
    with pytest.raises(ConfigError, match=f"{tmp_path}: is a directory, not a configuration file"):
        load_config(tmp_path)
    p = tmp_path / "c.toml"
    p.write_bytes(b"\xff\xfe[mavlink]\n")
    with pytest.raises(ConfigError, match="c.toml: not a text file"):
        load_config(p)


def test_run_with_a_directory_as_config_exits_2_without_traceback(tmp_path):
    import subprocess
    import sys
    r = subprocess.run([sys.executable, "-m", "companion", "run", "--config", str(tmp_path)],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2, r.stderr
    assert f"error: {tmp_path}: is a directory" in r.stderr and "Traceback" not in r.stderr


# ---------------------------------------------------------------------------------------------
# secrets

def test_redacted_hides_secrets_and_round_trips():
    from companion.config import REDACTED, config_from_dict, redacted, secret_keys
    cfg = loads_config("[corrections]\nsource = 'ntrip'\n[corrections.ntrip]\nmountpoint = 'M'\n"
                       "user = 'me'\npassword = 's3cret'\n")
    d = redacted(cfg)
    assert d["corrections"]["ntrip"]["password"] == REDACTED == "***"
    assert d["corrections"]["ntrip"]["user"] == "me" and d["corrections"]["ntrip"]["mountpoint"] == "M"
    assert "base_position_ecef_m" not in d["corrections"]             # unset optional: absent
    assert d["gnss"]["lever_arm_b_m"] == [0.0, 0.0, 0.0]
    assert "s3cret" not in repr(d) and "s3cret" not in cfg.to_toml(comments=False, redact=True)
    assert "s3cret" in cfg.to_toml(comments=False)                     # unredacted on request only
    back = config_from_dict(d)
    assert back.corrections.ntrip.password == "***"
    assert dataclasses.replace(back.corrections.ntrip, password="s3cret") == cfg.corrections.ntrip
    assert loads_config(cfg.to_toml(comments=False, redact=True)).corrections.ntrip.password == "***"
    assert redacted(Config())["corrections"]["ntrip"]["password"] == ""   # nothing to hide
    assert "corrections.ntrip.password" in secret_keys()


def test_every_password_or_token_key_is_marked_secret():
    for key, f, _ in _leaf_fields():
        if any(w in key.rsplit(".", 1)[-1] for w in ("password", "token", "secret", "passphrase")):
            assert f.metadata.get("secret"), f"{key} looks secret but is not marked secret=True"


def test_warns_when_a_file_with_a_password_is_readable_by_others(tmp_path):
    from companion.config import secrets_readable_by_others
    p = tmp_path / "c.toml"
    p.write_text("[corrections.ntrip]\npassword = 'pw'\n")
    p.chmod(0o644)
    w = secrets_readable_by_others(load_config(p))
    assert w and "corrections.ntrip.password" in w and "chmod 600" in w and "0644" in w
    p.chmod(0o600)
    assert secrets_readable_by_others(load_config(p)) is None
    q = tmp_path / "nopw.toml"
    q.write_text("")
    q.chmod(0o644)
    assert secrets_readable_by_others(load_config(q)) is None


# ---------------------------------------------------------------------------------------------
# companion config check / example, deploy/companion.toml

def _check(argv, capsys):
    from companion.cli import main
    rc = main(["config", *argv])
    out = capsys.readouterr()
    return rc, out.out, out.err


def test_config_check_ok_and_error(tmp_path, capsys):
    good, bad = tmp_path / "good.toml", tmp_path / "bad.toml"
    good.write_text("[output]\nrate_hz = 25\n")
    bad.write_text("[log]\nfsync_interval_s = 1e300\n")
    assert _check(["check", str(good)], capsys) == (0, f"{good}: OK\n", "")
    rc, out, err = _check(["check", str(bad)], capsys)
    assert rc == 2 and out == ""
    assert err == f"error: {bad}: log.fsync_interval_s: must be <= 60.0, got 1e+300\n"
    rc, out, err = _check(["check", str(good), str(tmp_path)], capsys)
    assert rc == 2 and f"{good}: OK" in out and "is a directory" in err


def test_config_example_is_accepted_by_check(tmp_path, capsys):
    rc, text, _ = _check(["example"], capsys)
    assert rc == 0 and text == example_config_toml()
    assert "# requested IMU message rate; allowed: 1.0 <= x <= 2000.0" in text
    p = tmp_path / "example.toml"
    p.write_text(text)
    assert _check(["check", str(p)], capsys)[0] == 0


def _keys_of(text: str) -> set[str]:
    import re
    keys, section = set(), ""
    for line in text.splitlines():
        if m := re.match(r"^\[([a-z_.]+)\]$", line):
            section = m.group(1) + "."
        elif m := re.match(r"^([a-z_0-9]+) = ", line) or re.match(r"^# ([a-z_0-9]+) = \.\.\.   \(optional", line):
            keys.add(section + m.group(1))
    return keys


def test_deploy_config_is_complete_and_valid(capsys):
    from pathlib import Path
    deploy = Path(__file__).resolve().parents[1] / "deploy" / "companion.toml"
    assert _check(["check", str(deploy)], capsys)[0] == 0
    example_keys = _keys_of(example_config_toml())
    assert example_keys == {k for k, _, _ in _leaf_fields()}
    missing = example_keys - _keys_of(deploy.read_text())
    assert not missing, f"deploy/companion.toml lacks {sorted(missing)} (regenerate from `companion config example`)"


def test_config_check_names_a_missing_extra(tmp_path, capsys, monkeypatch):
    import sys
    monkeypatch.setitem(sys.modules, "aiomqtt", None)          # as if aiomqtt were not installed
    p = tmp_path / "t.toml"
    p.write_text("[telemetry]\nenabled = true\n")
    rc, out, err = _check(["check", str(p)], capsys)
    assert rc == 2 and "telemetry.enabled = true needs aiomqtt" in err and "pip install 'companion[mqtt]'" in err


def test_imu_stream_names_agree_with_the_mavlink_decoder():
    """Every stream name the configuration accepts is one the decoder parses and decodes."""
    from companion.io import imu_streams, mavlink_decode
    for name in imu_streams.IMU_CLUSTER_STREAMS:
        message, unit = mavlink_decode.parse_imu_stream(name)
        assert unit is None or unit >= 0
        mavlink_decode.ImuDecoder(message, imu_id=unit)      # raises for a message it cannot decode
    with pytest.raises(ValueError):
        mavlink_decode.ImuDecoder("IMU_DATA")
    with pytest.raises(ValueError, match="unknown IMU stream"):
        mavlink_decode.parse_imu_stream("IMU_DATA")


def test_every_command_reports_a_config_error_without_traceback(tmp_path, capsys):
    from companion.cli import main
    assert main(["replay", str(tmp_path / "x.cflog"), "--config", str(tmp_path)]) == 2
    assert f"error: {tmp_path}: is a directory" in capsys.readouterr().err
