"""SAPIEN simulation of the Girona AUV and its docking station.

Modules:
    vehicle:   vehicle parameters, randomisation, Fossen hydrodynamics, ocean current, IMU
               (world NED / body FRD, NumPy only).
    thrusters: thruster geometry, allocation with uniform saturation, thrust curve, lag.
    physics:   the vehicle as a SAPIEN/PhysX rigid body at 300 Hz (the only place where the
               marine frames meet SAPIEN's z-up world and FLU actors).
"""
