"""The docking task as an environment: what the vehicle must do, what it measures and is paid,
one env step by step and many as arrays. The lowest room of ``rl``: it imports no other.

Modules:
    task:          target pose, error vector, visibility test, success criteria, spawn ranges.
    rewards:       the paper's reward as named terms (and ours, off by default).
    estimator:     the DS pose filter every observation source feeds.
    obs_sources:   how the DS pose is measured (``proxy``, ``acoustic``; the measurement types).
    error_model:   the ``error-model`` source: the camera pipeline's errors, fitted from images.
    camera_source: the ``camera`` source: render, water, the DS-pose estimator.
    observation:   the observation vector (the env's and the deployment runner's).
    curriculum:    the success test's tolerance and the spawn distance, eased over training.
    config:        ``EnvConfig``, the env's one config (nesting the components' configs).
    docking_env:   ``DockingEnv``, the Gymnasium env (``uwdock/Docking-v0``).
    batch_parts:   the step's maths over many envs at once (each the twin of a scalar piece).
    batch_env:     ``BatchDockingEnv``, N envs stepped as arrays (an SB3 ``VecEnv``).

Importing this package imports none of its modules (the vehicle install reads ``config``,
``observation`` and the filter without Gymnasium or SAPIEN).
"""
