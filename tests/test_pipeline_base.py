"""The pipeline's notion of "a base is sending": only corrections the engine can use count."""
import numpy as np

from companion.config import config_from_dict
from companion.messages import BaseStationPosition, GnssEpoch
from companion.pipeline import NavPipeline


def test_base_observations_before_the_station_position_are_not_a_base():
    """Joining a running caster midway, the first frame can be an MSM/1004 epoch before any
    1005: it must not switch the pipeline to waiting for base epochs (sitl attack, slow-header
    caster: the mode flipped tight/loose/tight and the filter re-initialised 3 times)."""
    pipe = NavPipeline(config_from_dict({}))
    pipe._feed_messages([GnssEpoch(1.4e9, (), "base")])
    assert not pipe.base_seen and pipe._base_times == []
    assert pipe.engine.counters["base epoch without station position"] == 1
    pipe._feed_messages([BaseStationPosition(7, np.array([-3947444.3, 3431514.0, 3638005.0])),
                         GnssEpoch(1.4e9 + 1.0, (), "base")])
    assert pipe.base_seen and pipe._base_times == [1.4e9 + 1.0]
