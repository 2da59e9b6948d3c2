"""Coordinate frames: a name plus one name per vector coordinate (notes, D.3.5)."""

from __future__ import annotations

import dataclasses


@dataclasses.dataclass(frozen=True)
class Frame:
    """The meaning of a vector signal: a frame name and a name for each coordinate.

    Frames are static metadata (hashable, never traced). Every input, state and output of a
    system has one; connecting systems checks that frames match.

    **Arguments:**

    - `name`: the frame's name, e.g. `"PendulumState"`.
    - `coordinates`: one name per element of the vector, e.g. `("theta", "thetadot")`.
    """

    name: str
    coordinates: tuple[str, ...]

    def __post_init__(self):
        object.__setattr__(self, "coordinates", tuple(str(c) for c in self.coordinates))
        if len(set(self.coordinates)) != len(self.coordinates):
            raise ValueError(f"frame {self.name!r} repeats a coordinate name: {self.coordinates}")

    @classmethod
    def default(cls, name: str, size: int, prefix: str) -> "Frame":
        """A frame with coordinates `prefix0, prefix1, ...`."""
        return cls(name, tuple(f"{prefix}{i}" for i in range(size)))

    @property
    def dim(self) -> int:
        return len(self.coordinates)

    def index(self, coordinate: str) -> int:
        """The position of a named coordinate."""
        try:
            return self.coordinates.index(coordinate)
        except ValueError:
            raise KeyError(f"frame {self.name!r} has no coordinate {coordinate!r}; "
                           f"it has {self.coordinates}") from None

    def __str__(self) -> str:
        return f"{self.name}({', '.join(self.coordinates)})"
