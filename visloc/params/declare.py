"""How a parameter is declared: once, as a dataclass field with its unit, range, help and users.

``param(default, help=..., unit=..., ...)`` makes a dataclass field whose ``Spec`` (in the field's
metadata) is everything the rest of visloc needs to know about it:

* ``check(obj)`` validates every declared field of a parameter object and raises a
  ``ParameterError`` naming the parameter (``err.params`` holds its name);
* the command line makes one flag per declared field with a ``flag`` (``visloc.cli.parser``), its help
  text and default from here, and names the flag when a value is refused (``flag_of``);
* the dashboard makes one control per field with a ``Control`` (``visloc.dashboard.gui``);
* ``docs/parameters.md`` is ``parameter_table_markdown()`` (a test keeps them equal).

Adding a parameter is adding its field here and the code that uses it.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import MISSING, asdict, dataclass, field, fields, replace

from visloc.errors import ParameterError

METHODS_ALL = ("paper", "refined", "refined-fast")  # the named methods (visloc.tracking.methods)
MAX_C_INT = 2**31 - 1  # integers handed to OpenCV
AUTO = "auto"  # a Spec's flag: "--" and the field's name with dashes
MIN_VARIANCE, MAX_VARIANCE = 1e-12, 1e12  # a positive R, Q or P0, in its units (keeps the filter's numbers finite)


@dataclass(frozen=True)
class Control:
    """A dashboard control for a parameter: a slider.

    label:   the slider's label
    low, high, step: the slider's range and step, in what it shows
    folder:  "matching" (a change re-matches every query in the background) or "filter" (a change
             re-runs the filter only, at once) or "queries" (which queries and candidates: re-matches)
    shows:   "value" (the parameter itself) or "sigma" (its square root: a variance shown as a
             standard deviation)
    initial: the slider's first value in parameter units (None: the field's default)
    hint:    the hover text (None: the parameter's help)
    """

    label: str
    low: float
    high: float
    step: float
    folder: str
    shows: str = "value"
    initial: float | None = None
    hint: str | None = None

    def to_shown(self, value: float) -> float:
        return math.sqrt(value) if self.shows == "sigma" else value

    def from_shown(self, shown: float) -> float:
        return shown * shown if self.shows == "sigma" else shown


@dataclass(frozen=True)
class Spec:
    """What a parameter is.

    help:    one line for users: what it does (``--help``, the docs, the dashboard's hint)
    unit:    "s", "m", "m^2", "px", "deg", ... ("" for a pure number)
    kind:    "number", "integer", "variance" (0 or in [MIN_VARIANCE, MAX_VARIANCE]), "bool",
             "choice", "distances" (a non-empty tuple of distances > 0)
    low, high, open_low, open_high: the allowed range (None: unbounded on that side)
    choices: a "choice" parameter's values
    methods: the methods it affects (``METHODS_ALL`` by default); "ingest", "track" for those stages
    flag:    its command-line flag (``AUTO``: from its name; None: not on the command line)
    when_unset: what None means for it (the command chooses: "number of cores", ...); None: None is refused
    symbol:  how the paper writes it ("R", "Q", "P0"), named beside it in messages
    control: its dashboard control, if it has one
    """

    help: str
    unit: str = ""
    kind: str = "number"
    low: float | None = None
    high: float | None = None
    open_low: bool = False
    open_high: bool = False
    choices: tuple[str, ...] = ()
    methods: tuple[str, ...] = METHODS_ALL
    flag: str | None = AUTO
    when_unset: str | None = None
    symbol: str = ""
    control: Control | None = None

    def rule(self) -> str:
        """What a valid value is, in words and its unit: "in (0, 1]", "an integer >= 1", "> 0 m", ..."""
        unit = f" {self.unit}" if self.unit else ""
        if self.kind == "variance":
            return f">= 0 (0 or in [{MIN_VARIANCE:g}, {MAX_VARIANCE:g}]){unit}"
        if self.kind == "bool":
            return "True or False"
        if self.kind == "choice":
            return "one of " + ", ".join(self.choices)
        if self.kind == "distances":
            return f"a non-empty tuple of distances > 0{unit}"
        what = "an integer " if self.kind == "integer" else ""
        low, high = (str(int(b)) if self.kind == "integer" and b is not None else f"{b:g}" if b is not None else ""
                     for b in (self.low, self.high))
        if self.low is not None and self.high is not None:
            return f"{what}in {'(' if self.open_low else '['}{low}, {high}{')' if self.open_high else ']'}{unit}"
        if self.low is not None:
            return f"{what}{'>' if self.open_low else '>='} {low}{unit}"
        if self.high is not None:
            return f"{what}{'<' if self.open_high else '<='} {high}{unit}"
        return f"{what}finite".strip()

    def accepts(self, value) -> bool:
        if value is None:
            return self.when_unset is not None
        if self.kind == "bool":
            return isinstance(value, bool)
        if self.kind == "choice":
            return value in self.choices
        if self.kind == "distances":
            return isinstance(value, tuple) and bool(value) and all(
                isinstance(b, (int, float)) and not isinstance(b, bool) and math.isfinite(b) and b > 0 for b in value)
        if self.kind == "integer" and (not isinstance(value, int) or isinstance(value, bool)):
            return False
        if not (isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)):
            return False
        if self.kind == "variance":
            return value == 0 or MIN_VARIANCE <= value <= MAX_VARIANCE
        if self.low is not None and (value <= self.low if self.open_low else value < self.low):
            return False
        return not (self.high is not None and (value >= self.high if self.open_high else value > self.high))


def param(default, help: str, **spec):
    """A declared dataclass field: ``default`` and the ``Spec`` made of ``help`` and ``spec``."""
    return field(default=default, metadata={"spec": Spec(help=help, **spec)})


def value_text(value) -> str:
    """A parameter's value as a user types it (a tuple comma-separated), for help texts and the docs."""
    if isinstance(value, tuple):
        return ",".join(f"{v:g}" for v in value)
    if isinstance(value, float):
        return f"{value:.6g}"
    return str(value)


def refuse(message: str, *names: str) -> ParameterError:
    """A ``ParameterError``; ``names`` (the fields at fault) let the command line name its flags."""
    err = ParameterError(message)
    err.params = names  # type: ignore[attr-defined]
    return err


def declared(cls_or_obj) -> Iterator[tuple[str, Spec, object]]:
    """(name, spec, default) of every declared field, in declaration order."""
    for f in fields(cls_or_obj):
        if "spec" in f.metadata:
            yield f.name, f.metadata["spec"], (None if f.default is MISSING else f.default)


def spec_of(cls_or_obj, name: str) -> Spec:
    for n, spec, _ in declared(cls_or_obj):
        if n == name:
            return spec
    raise KeyError(name)


def refusal(name: str, spec: Spec, value) -> ParameterError:
    """The ``ParameterError`` that refuses ``value`` for the declared field ``name``, saying what is valid."""
    shown = f"{name} ({spec.symbol})" if spec.symbol else name
    return refuse(f"{shown}={value!r}: must be {spec.rule()}", name)


def check(obj) -> None:
    """Validate every declared field of ``obj``: the first that is out of range is refused, naming it."""
    for name, spec, _ in declared(obj):
        value = getattr(obj, name)
        if not spec.accepts(value):
            raise refusal(name, spec, value)


def flag_of(name: str, spec: Spec) -> str | None:
    """The command-line flag of a declared field (None: it has none)."""
    if spec.flag is None:
        return None
    return "--" + name.replace("_", "-") if spec.flag == AUTO else spec.flag


class Params:
    """Base of every parameter class: frozen, declared fields, validated on creation."""

    def __post_init__(self) -> None:
        check(self)

    def as_dict(self) -> dict:
        return asdict(self)  # type: ignore[call-overload]

    def replace(self, **changes):
        names = {f.name for f in fields(self)}  # type: ignore[arg-type]
        unknown = set(changes) - names
        if unknown:
            raise ParameterError(f"unknown parameter {sorted(unknown)[0]!r} for {type(self).__name__}")
        return replace(self, **changes)  # type: ignore[type-var]
