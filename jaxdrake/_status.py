"""The result convention: every result has a `status` (a `StatusCode` member, or an array of
codes inside `jit` / `vmap`), and `success` and `message` from it (`Reported`)."""

from __future__ import annotations

import enum
import functools
import operator
from typing import ClassVar

import numpy as np


class StatusCode(enum.IntEnum):
    """A status code that carries its message (what happened and the usual remedy). A
    subclass lists its codes, then declares them once: `Cls.describe(messages, successes)`."""

    @classmethod
    def describe(cls, messages: dict, successes=(0,)):
        missing = [code.name for code in cls if code not in messages]
        if missing:
            raise TypeError(f"{cls.__name__}: no message for {missing}")
        cls._messages = dict(messages)
        cls._successes = tuple(cls(code) for code in successes)

    @property
    def message(self) -> str:
        return self._messages[self]

    @property
    def success(self) -> bool:
        return self in self._successes

    @classmethod
    def is_success(cls, status):
        """Whether `status` (a code, or an array of codes: traced and batched too) is a success."""
        return functools.reduce(operator.or_, [status == code for code in cls._successes])

    @classmethod
    def message_of(cls, status):
        """The message of a code, or an array of messages (the shape of `status`) for a batch."""
        codes = np.asarray(status)
        if codes.ndim == 0:
            return cls(int(codes)).message
        return np.vectorize(lambda code: cls(int(code)).message, otypes=[object])(codes)


class Reported:
    """`success` and `message` of a result from its `status`, whose codes are `status_type`'s."""

    status_type: ClassVar[type[StatusCode]]

    @property
    def success(self):
        return self.status_type.is_success(self.status)

    @property
    def message(self):
        return self.status_type.message_of(self.status)
