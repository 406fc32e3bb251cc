"""ROS 2 on the wire without a ROS installation: the Jazzy message types and their CDR bytes
(through ``rosbags``' type store), conversions between messages and the toolkit's arrays
(``T_a_b`` poses, NED/FRD or ENU/FLU per REP 103), DDS participants that ROS 2 graphs see
(Cyclone DDS, ``rt/<topic>``, ``<pkg>::msg::dds_::<Type>_``; loopback-only by default) and MCAP
recordings with ``ros2msg`` schemas.

Modules:
    messages:    the type store, CDR, builders and readers of the messages the node uses.
    conventions: world/body axis conventions (NED/FRD, ENU/FLU) converted in one place.
    dds:         Cyclone DDS participants, QoS profiles, loopback configuration.
    mcap:        MCAP recordings (write; read back through ``dockcore.bags``).
"""

if __name__ != "uwdock.ros":  # this folder reached as a top-level name (the working directory)
    raise ImportError(
        "this folder is installed as uwdock.ros: import uwdock.ros "
        "(pip install -e . from the repository puts it there)"
    )
