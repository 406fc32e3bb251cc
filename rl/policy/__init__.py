"""Policies: a trained policy as data on disk, loaded and run as a controller, the classical
baseline beside it, the env a policy was trained in, and its ONNX export. Imports the env's
room (``rl.env``: the observation layout) and no room above it.

Modules:
    policy_format:  the policy file format (``model.json`` + ``weights.npz``, no pickles).
    asymmetric:     the asymmetric actor-critic (SB3 and torch at module level).
    baselines:      the PID baseline, reading the policy's observation.
    policy_io:      policy folders and ``.onnx`` files, their training env, the controllers.
    env_settings:   the env a command runs a policy in, and where each setting came from.
    export:         ``rl export``: the policy as ONNX (``export_actor``: the exported network).
    policy_convert: ``rl convert-policy``: a pickled-format folder in the data format.
"""
