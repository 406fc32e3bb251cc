"""The policy on a vehicle: the docking node on ROS 2 topics, recorded missions replayed, and the
simulator as the vehicle over the same middleware.

Modules:
    runner:  camera frames and odometry in, the policy's wrench out (no ROS, no simulator).
    config:  the node's settings (topics, frames, QoS, axes, safety), ``profiles/*.toml``.
    inputs:  messages read and checked into the toolkit's frames.
    chain:   the docking chain without a transport: inputs by stamp, a tick at the policy's
             rate, the command or the reason it holds.
    wire:    which topics the chain reads and what a tick publishes (node and replay share it).
    node:    ``rl node``: the chain on DDS (Cyclone, no ROS installation).
    replay:  ``rl replay``: a bag through the chain on message time.
    vehicle: ``sim vehicle``: the docking env speaking ROS 2 topics (needs ``uwdock[rl]``).
    cli:     the three commands.

``rl node`` and ``rl replay`` need ``uwdock[vehicle]`` only: no torch, no SAPIEN, no Gymnasium
(the policy runs as ONNX through onnxruntime, and loading it runs no code from its folder).
A room of ``rl`` above ``rl.env``, ``rl.policy`` and ``rl.evaluate`` (the simulated vehicle
counts its episodes as an evaluation does); ``rl.train`` is its peer.
"""
