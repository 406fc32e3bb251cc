"""Value domains shared by the simulator's configuration fields (see :mod:`dockcore.domains`).

Bounds are physical: generous enough for any vehicle, tank or camera the toolkit models, tight
enough that a typo (``1e12`` for ``1e2``) is refused before it blows up memory, time or the
integrator.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Annotated, Any

from uwdock.dockcore.domains import Fraction, Interval

__all__ = [
    "RGB",
    "TANK_SIZE_M",
    "BodyCoord_m",
    "Friction",
    "RelativeRange",
    "TankSide_m",
    "validate_each",
]

#: A linear RGB colour (albedo or tint), each channel in [0, 1].
RGB = tuple[Fraction, Fraction, Fraction]

#: A coordinate of a point on the vehicle, in its body or camera frame (m); the Girona AUV
#: is 1.5 m long.
BodyCoord_m = Annotated[float, Interval(ge=-10, le=10)]

#: A Coulomb friction coefficient (-); rubber on concrete is about 1.
Friction = Annotated[float, Interval(ge=0, le=5)]

#: A relative randomisation range r (-): a value is scaled by 1 + U(-r, r), so r < 1 keeps it
#: positive.
RelativeRange = Annotated[float, Interval(ge=0, lt=1)]

#: A side of the test tank (m): length, width or water depth.
TankSide_m = Annotated[float, Interval(gt=0, le=1000)]

#: The test tank of the reference: length (world x), width (world y), water depth (m). The one
#: default of the env, the DS scene and the dataset pose sampler.
TANK_SIZE_M: tuple[float, float, float] = (19.0, 9.0, 5.0)


def validate_each(name: str, items: Iterable[Any]) -> None:
    """Call ``validate()`` of each item of the tuple field ``name``; a ValueError names the item
    (``thrusters[2].axis: ...``)."""
    for i, item in enumerate(items):
        try:
            item.validate()
        except ValueError as exc:
            raise ValueError(f"{name}[{i}].{exc}") from None
