"""Named parameters: symbols, values, derived parameters and overrides."""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable, Mapping

import casadi as ca

from ..errors import ParameterError

DerivedRule = Callable[[Mapping[str, float]], float]


def resolve_params(
    defaults: Mapping[str, float],
    derived: Mapping[str, DerivedRule] | None = None,
    overrides: Mapping[str, float] | None = None,
) -> dict[str, float]:
    """Resolve parameter values with derived parameters.

    A derived parameter (e.g. ``X3 = L3/2``) follows its base parameters
    when those are overridden, unless it is overridden itself.

    Raises
    ------
    ParameterError
        Unknown names, or non-finite values.
    """
    derived = dict(derived or {})
    overrides = dict(overrides or {})
    unknown = sorted(set(overrides) - set(defaults))
    if unknown:
        raise ParameterError(
            f"unknown parameter(s) {unknown}; known parameters are {sorted(defaults)}"
        )
    values = {k: float(v) for k, v in defaults.items()}
    values.update({k: float(v) for k, v in overrides.items()})
    for name, rule in derived.items():
        if name not in overrides:
            values[name] = float(rule(values))
    bad = {k: v for k, v in values.items() if not math.isfinite(v)}
    if bad:
        raise ParameterError(f"parameter values must be finite, got {bad}")
    return values


def parse_assignments(items: list[str] | None, *, option: str = "--set",
                      words: bool = False) -> dict[str, float | str]:
    """Parse ``name=value`` strings from a command line (never ``eval``-ed).

    With ``words``, a value that is an identifier-like word (``coordinates=cartesian``) is kept as
    that string, for the scene's ``choices`` to check; anything else must be a number."""
    out: dict[str, float | str] = {}
    for item in items or []:
        if "=" not in item:
            raise ParameterError(f"{option} expects name=value, got {item!r}")
        name, _, text = item.partition("=")
        name = name.strip()
        try:
            out[name] = float(text)
        except ValueError:
            if words and text.strip().isidentifier():
                out[name] = text.strip()
                continue
            raise ParameterError(
                f"{option} {item!r}: value {text!r} is not a number"
            ) from None
    return out


@dataclass
class ParamSet:
    """Symbols for named parameters, in a fixed order.

    ``P = ParamSet(["m1", "L1"]); P["m1"]`` is the CasADi symbol; ``P.sym`` the
    column of all of them (the ``theta`` input of every model Function).
    """

    names: list[str]
    sym: ca.SX = field(init=False)

    def __post_init__(self) -> None:
        self.names = list(self.names)
        if len(set(self.names)) != len(self.names):
            raise ParameterError(f"duplicate parameter names in {self.names}")
        self.sym = ca.SX.sym("theta", len(self.names))

    def __getitem__(self, name: str) -> ca.SX:
        try:
            return self.sym[self.names.index(name)]
        except ValueError:
            raise ParameterError(f"unknown parameter {name!r}; known: {self.names}") from None

    def __iter__(self):
        return iter(self.names)

    def __len__(self) -> int:
        return len(self.names)
