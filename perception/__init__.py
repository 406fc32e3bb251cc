"""Perception: camera image -> marker detections -> docking-station pose.

* :mod:`perception.preprocess`: named preprocessing pipelines (``default``, the published
  ``reference_3dbm``, ``threshold_sweep``, ``normalise_invert``, and ``plain``).
* :mod:`perception.detector`: :class:`~perception.detector.Detector` (OpenCV ArUco / AprilTag).
* :mod:`perception.pose`: single-marker IPPE with both solutions, and the joint board PnP
  with outlier rejection and a covariance.
* :mod:`perception.ds_pose`: THE docking-station pose estimator (detector + board PnP +
  level-DS refinement given the attitude + prior), used by ``perception eval``, the env's camera
  source, the error-model fit and the deployment runner. Its images are BGR (OpenCV's order).

Imports only numpy, OpenCV, ``calibration``, ``markers`` and ``dockcore``: never SAPIEN, torch,
``sim`` or ``rl``, so footage can be evaluated without the simulator.
"""

if (
    __name__ != "uwdock.perception"
):  # this folder reached as a top-level name (the working directory)
    raise ImportError(
        "this folder is installed as uwdock.perception: import uwdock.perception "
        "(pip install -e . from the repository puts it there)"
    )
