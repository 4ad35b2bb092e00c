"""Ground mode of the pipeline (ZUPT/NHC on the ground only), from real MAVLink bytes."""
import os

os.environ.setdefault("MAVLINK20", "1")
from pymavlink.dialects.v20 import ardupilotmega as mav  # noqa: E402

from companion.config import config_from_dict  # noqa: E402
from companion.pipeline import NavPipeline  # noqa: E402

ENC = mav.MAVLink(None, srcSystem=1, srcComponent=1)


def _feed(pipe, msg):
    pipe.feed("mavlink", 0, bytes(msg.pack(ENC)))


def _hb(vehicle_type, status):
    return mav.MAVLink_heartbeat_message(vehicle_type, mav.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, status, 3)


def test_ground_mode_follows_vehicle_type_landed_state_and_arming():
    pipe = NavPipeline(config_from_dict({"filter": {"nhc_enabled": True}}))
    assert pipe.engine.cfg.nhc_enabled
    assert not pipe.engine.ground_mode                       # unknown vehicle: no NHC
    # a copter: disarmed = on the ground, armed = flying (no landed state reported)
    _feed(pipe, _hb(mav.MAV_TYPE_QUADROTOR, mav.MAV_STATE_STANDBY))
    assert pipe.engine.ground_mode
    _feed(pipe, _hb(mav.MAV_TYPE_QUADROTOR, mav.MAV_STATE_ACTIVE))
    assert not pipe.engine.ground_mode
    # the landed state, once reported, wins: a plane taxiing armed is on the ground
    _feed(pipe, mav.MAVLink_extended_sys_state_message(0, mav.MAV_LANDED_STATE_ON_GROUND))
    assert pipe.engine.ground_mode
    _feed(pipe, mav.MAVLink_extended_sys_state_message(0, mav.MAV_LANDED_STATE_TAKEOFF))
    assert not pipe.engine.ground_mode
    # a rover (or boat) is always on the ground, armed or not
    _feed(pipe, _hb(mav.MAV_TYPE_GROUND_ROVER, mav.MAV_STATE_ACTIVE))
    assert pipe.engine.ground_mode
    assert pipe.counters["ground mode on"] == 3 and pipe.counters["ground mode off (airborne)"] == 2
    # a message from another component (a gimbal's heartbeat) changes nothing
    other = mav.MAVLink(None, srcSystem=1, srcComponent=154)
    pipe.feed("mavlink", 0, bytes(_hb(mav.MAV_TYPE_GIMBAL, mav.MAV_STATE_ACTIVE).pack(other)))
    assert pipe.engine.ground_mode


def test_nhc_and_landed_state_stream_are_configurable():
    from companion.io.mavlink import message_rates_from_config
    cfg = config_from_dict({"filter": {"nhc_enabled": True, "nhc_sigma_lateral_mps": 0.2}})
    eng = cfg.engine_config()
    assert eng.nhc_enabled and eng.nhc_sigma_lateral_mps == 0.2
    assert message_rates_from_config(cfg.mavlink)["EXTENDED_SYS_STATE"] == 1.0
    assert not config_from_dict({}).engine_config().nhc_enabled
