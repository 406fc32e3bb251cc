"""Quality of service of a ROS 2 topic, as a config table (no DDS library needed to read it).

The names are ROS 2's (``rclpy.qos``): reliability, history depth (keep last N), durability.
:func:`uwdock.ros.dds.dds_qos` turns a profile into Cyclone DDS's QoS.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated, Literal

from uwdock.dockcore.domains import Interval

__all__ = ["RELIABLE", "SENSOR_DATA", "QosProfile"]


@dataclass(frozen=True)
class QosProfile:
    """The QoS of one topic, in ROS 2's terms.

    Attributes:
        reliability: ``"best_effort"`` (sensor data: a lost sample is not resent) or
            ``"reliable"``.
        depth: history depth (keep last N); the reader keeps the newest N samples.
        durability: ``"volatile"`` or ``"transient_local"`` (a late reader gets the writer's
            last ``depth`` samples: latched topics such as ``camera_info``).
    """

    reliability: Literal["best_effort", "reliable"] = "reliable"
    depth: Annotated[int, Interval(ge=1, le=10_000)] = 10
    durability: Literal["volatile", "transient_local"] = "volatile"

    def validate(self) -> None:
        """Raise ValueError on a value ROS 2 has no name for."""
        if self.reliability not in ("best_effort", "reliable"):
            raise ValueError(f"reliability must be best_effort or reliable: {self.reliability!r}")
        if self.durability not in ("volatile", "transient_local"):
            raise ValueError(f"durability must be volatile or transient_local: {self.durability!r}")
        if isinstance(self.depth, bool) or not isinstance(self.depth, int) or self.depth < 1:
            raise ValueError(f"depth must be an integer >= 1, got {self.depth!r}")


#: ROS 2's sensor-data profile (rmw_qos_profile_sensor_data): best effort, keep last 5; the
#: node's default for camera and navigation is keep last 1 (only the latest frame matters).
SENSOR_DATA = QosProfile("best_effort", 1, "volatile")
#: ROS 2's default profile for commands and state: reliable, keep last 10.
RELIABLE = QosProfile("reliable", 10, "volatile")
