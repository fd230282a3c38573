"""The options a model component declares for its spec: type, range, unit (``pi(n=16)``)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class Option:
    """One option of a spec component: ``kind`` ``int``, ``number`` or ``choice``; range and unit."""

    kind: str
    default: Any = None
    minimum: float | None = None
    maximum: float | None = None
    exclusive_minimum: bool = False
    choices: tuple[str, ...] = ()
    unit: str = ""
    doc: str = ""

    def expected(self) -> str:
        if self.kind == "choice":
            return "one of " + ", ".join(self.choices)
        if self.kind == "text":
            return "a name"
        if self.kind == "int":
            if self.minimum == 1 and self.maximum is None:
                text = "a positive integer (at least 1)"
            elif self.minimum == 0 and self.maximum is None:
                text = "an integer >= 0"
            else:
                text = "an integer"
        else:
            text = "a finite number"
        unit = f" {self.unit}" if self.unit else ""
        low = None if self.minimum is None or (self.kind == "int" and self.maximum is None and self.minimum in (0, 1)) \
            else f"{'>' if self.exclusive_minimum else '>='} {self.minimum:g}{unit}"
        high = None if self.maximum is None else f"<= {self.maximum:g}{unit}"
        bounds = " and ".join(b for b in (low, high) if b)
        if bounds:
            text += f" {bounds}"
        elif unit:
            text += f" (in{unit})"
        return text

    def check(self, value: Any) -> Any:
        """The value, typed; raises ValueError with what was expected."""
        if self.kind == "choice":
            if isinstance(value, str) and value in self.choices:
                return value
            raise ValueError(self.expected())
        if self.kind == "text":
            if isinstance(value, str) and value:
                return value
            raise ValueError(self.expected())
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ValueError(self.expected())
        if self.kind == "int" and not isinstance(value, int):
            raise ValueError(self.expected() + " (no fractions)")
        if isinstance(value, float) and not math.isfinite(value):
            raise ValueError(self.expected())
        if self.minimum is not None and (value < self.minimum or (self.exclusive_minimum and value == self.minimum)):
            raise ValueError(self.expected())
        if self.maximum is not None and value > self.maximum:
            raise ValueError(self.expected())
        return value  # an int given to a number option stays as written (the canonical spec keeps it)
