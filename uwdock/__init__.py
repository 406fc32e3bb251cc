"""uwdock: vision-in-the-loop underwater docking.

The repository's top-level folders are installed as subpackages of this one namespace, so no
generic name (``datasets``, ``sim``, ``rl`` ...) is claimed in a user's environment:

=====================  ===========================================================  =========
import name            what it owns                                                 extra
=====================  ===========================================================  =========
``uwdock.dockcore``    config dataclasses, value domains, atomic writes, CLI rules   (base)
``uwdock.markers``     3D Binary Markers: dictionaries, printable STL/PDF/SVG        (base)
``uwdock.calibration`` camera models and files, intrinsics, extrinsics, frames       (base)
``uwdock.perception``  3DBM detector, the DS-pose estimator, ``perception eval``     (base)
``uwdock.sim``         SAPIEN world, vehicle physics, the underwater camera          ``sim``
``uwdock.datasets``    synthetic datasets, loaders for real footage                  ``sim``
``uwdock.rl``          Gymnasium env, observation sources, PPO, evaluation, export   ``rl``
=====================  ===========================================================  =========

``pip install uwdock`` gives the footage tools (markers, perception, calibration) without SAPIEN,
torch or Stable-Baselines3; ``uwdock[sim]`` adds the simulator, ``uwdock[rl]`` (or ``[all]``) the
learning stack.
"""

#: The one place of the version: ``pyproject.toml`` reads it from here (setuptools' ``attr:``,
#: without importing), so importing ``uwdock`` needs no ``importlib.metadata`` (60 ms of every
#: command's start-up).
__version__ = "0.1.0"

#: Who may import whom: each subpackage's rank; a module may import only subpackages of a lower
#: rank (perception and sim are peers and never import each other). ``tests/test_architecture.py``
#: walks every import of the tree against this table.
LAYERS = {
    "dockcore": 0,
    "calibration": 1,
    "markers": 2,
    "ros": 2,
    "perception": 3,
    "sim": 3,
    "datasets": 4,
    "rl": 5,
}

#: The rooms of a package split into sub-packages (the package's own modules count as rooms
#: too): each room's rank inside its package. A module may import only rooms of a lower rank
#: (two rooms of one rank are peers and never import each other); the package's ``__init__``
#: sits below every room. A package not named here is one room (no sub-packages).
#: ``tests/test_architecture.py`` checks it.
ROOMS = {
    "rl": {"env": 0, "policy": 1, "evaluate": 2, "train": 3, "deploy": 3, "cli": 4},
}
