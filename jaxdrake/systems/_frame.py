"""Coordinate frames: a name plus one name per vector coordinate (notes, D.3.5).

Connecting an output to an input checks their frames. A coordinate transform between two
named frames is registered once with `add_frame_conversion`; combinators then insert it
automatically where the output's frame differs from the input's.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable


@dataclasses.dataclass(frozen=True)
class Frame:
    """The meaning of a vector signal: a frame name and a name for each coordinate.

    Frames are static metadata (hashable, never traced). Every input, state and output of a
    system has one; connecting systems checks that frames match.

    **Arguments:**

    - `name`: the frame's name, e.g. `"PendulumState"`.
    - `coordinates`: one name per element of the vector, e.g. `("theta", "thetadot")`.
    - `generic`: True for the placeholder frames a system gets when it names none
      (`Frame.default`); a generic frame connects to any frame of the same size.
    - `coder`: an LCM coder (`jaxdrake.lcm`) for this frame's vectors, set by `with_coder`;
      not part of the frame's identity.
    """

    name: str
    coordinates: tuple[str, ...]
    generic: bool = dataclasses.field(default=False, compare=False)
    coder: object = dataclasses.field(default=None, compare=False, repr=False)

    def __post_init__(self):
        object.__setattr__(self, "coordinates", tuple(str(c) for c in self.coordinates))
        if len(set(self.coordinates)) != len(self.coordinates):
            raise ValueError(f"frame {self.name!r} repeats a coordinate name: {self.coordinates}")

    @classmethod
    def default(cls, name: str, size: int, prefix: str) -> "Frame":
        """A generic frame with coordinates `prefix0, prefix1, ...`."""
        return cls(name, tuple(f"{prefix}{i}" for i in range(size)), generic=True)

    def with_coder(self, coder) -> "Frame":
        """This frame carrying an LCM `coder` (its vectors must have this frame's size), so a
        port with this frame maps to an LCM channel."""
        if coder.dim != self.dim:
            raise ValueError(f"a coder of {coder.dim} coordinates ({coder.frame}) cannot carry frame {self}")
        return dataclasses.replace(self, coder=coder)

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


_CONVERSIONS: dict[tuple[Frame, Frame], Callable] = {}


def add_frame_conversion(source: Frame, target: Frame, transform: Callable) -> None:
    """Register a coordinate transform `y_target = transform(y_source)` (a JAX function of one
    vector) between two frames, the notes' `addTransform`. Connections made after this from
    an output in `source` to an input in `target` apply it. A system built before keeps the
    transform it was built with (it is static structure of that system)."""
    for role, f in (("source", source), ("target", target)):
        if not isinstance(f, Frame):
            raise TypeError(f"add_frame_conversion: {role} must be a jaxdrake.Frame, got {type(f).__name__}")
    if not callable(transform):
        raise TypeError("add_frame_conversion: transform must be a function of one vector")
    _CONVERSIONS[(source, target)] = transform


def frame_conversion(source: Frame, target: Frame) -> Callable | None:
    """How an output in frame `source` enters an input in frame `target`: None when they are
    the same (or one is generic and the sizes agree), the registered transform when there is
    one; otherwise a ValueError naming both frames and their coordinates."""
    if source == target or ((source.generic or target.generic) and source.dim == target.dim):
        return None
    if (source, target) in _CONVERSIONS:
        return _CONVERSIONS[(source, target)]
    if source.dim != target.dim:
        raise ValueError(f"cannot connect an output in frame {source} ({source.dim} coordinates) to "
                         f"an input in frame {target} ({target.dim} coordinates): the sizes differ")
    raise ValueError(f"cannot connect an output in frame {source} to an input in frame {target}: "
                     "the frames differ and no conversion between them is registered "
                     "(jaxdrake.add_frame_conversion)")
