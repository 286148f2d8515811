"""Command-line flags made from the parameters' declarations (``visloc.params``), and back.

``add_param_flags`` adds one flag per declared field of a parameter class that has a flag, with
its help, unit, valid range and default from the declaration; ``changes_from_flags`` reads back
the values the user gave; ``flags_named`` re-raises a refused value naming the flag typed.
A new declared parameter gets its flag, its ``--help`` line and its message without a change here.
"""

from __future__ import annotations

import argparse
from collections.abc import Iterable, Iterator
from contextlib import contextmanager

from visloc.errors import ParameterError
from visloc.params import PARAMETER_CLASSES, Spec, declared, flag_of, refusal, value_text

# flag of every declared parameter, by field name (a name two classes share has one flag)
FLAGS = {name: flag for cls in PARAMETER_CLASSES for name, spec, _ in declared(cls)
         if (flag := flag_of(name, spec)) is not None}
# the declarations of each flagged field name, in every class that has it
SPECS = {name: [spec for cls in PARAMETER_CLASSES for n, spec, _ in declared(cls) if n == name] for name in FLAGS}


def dest_of(flag: str) -> str:
    return flag.lstrip("-").replace("-", "_")


def _distances(text: str) -> tuple[float, ...]:
    try:
        return tuple(float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: expected distances separated by commas, e.g. 2,5,10") from None


def help_of(spec: Spec, default_text: str | None) -> str:
    """A flag's help: what it does, its valid values and unit, its default."""
    text = f"{spec.help}; {spec.rule()}"
    text = text.replace("%", "%%")  # argparse formats help with %
    return text if default_text is None else f"{text} (default {default_text})"


def default_text_of(spec: Spec, value) -> str:
    """A default as ``--help`` and the docs show it: its value, or what None means for it."""
    return spec.when_unset if value is None and spec.when_unset else value_text(value)


def add_param_flags(group, cls, preset=None, *, presets: Iterable[tuple[str, object]] = (),
                    exclude: Iterable[str] = (), automatic: dict[str, str] | None = None,
                    only: Iterable[str] | None = None) -> None:
    """One flag per declared field of ``cls`` that has one.

    preset:    the parameter object whose values are the defaults; None: the flags default to None, "the
               method's own", and ``presets`` (label, parameter object) say what that is per method
    exclude:   fields this command sets itself
    only:      the fields this command takes (None: every field)
    automatic: field -> help of a flag whose default (None) the command chooses from the data
    """
    automatic = automatic or {}
    presets = list(presets)
    only = None if only is None else set(only)
    for name, spec, _ in declared(cls):
        flag = flag_of(name, spec)
        if flag is None or name in exclude or (only is not None and name not in only):
            continue
        kwargs: dict = {"dest": dest_of(flag), "default": None}
        if spec.kind == "bool":
            kwargs["action"] = argparse.BooleanOptionalAction
        elif spec.kind == "choice":
            kwargs["choices"] = spec.choices
        else:
            kwargs["type"] = {"integer": int, "distances": _distances}.get(spec.kind, float)
        if name in automatic:
            kwargs["help"] = automatic[name]
        elif preset is not None:
            kwargs["default"] = getattr(preset, name)
            kwargs["help"] = help_of(spec, default_text_of(spec, kwargs["default"]))
        else:
            values = [(label, getattr(p, name)) for label, p in presets]
            if len({value_text(v) for _, v in values}) <= 1:
                default_text = value_text(values[0][1]) if values else None
            else:
                default_text = "the method's: " + ", ".join(f"{label} {value_text(v)}" for label, v in values)
            kwargs["help"] = help_of(spec, default_text)
        group.add_argument(flag, **kwargs)


def changes_from_flags(a: argparse.Namespace, cls, exclude: Iterable[str] = ()) -> dict:
    """The fields of ``cls`` the user set by flag (a flag left at None is left to the preset)."""
    out = {}
    for name, spec, _ in declared(cls):
        flag = flag_of(name, spec)
        if flag is None or name in exclude:
            continue
        value = getattr(a, dest_of(flag), None)
        if value is not None:
            out[name] = value
    return out


@contextmanager
def flags_named() -> Iterator[None]:
    """Parameters built from flags: a ``ParameterError`` is re-raised starting with the flags at fault."""
    try:
        yield
    except ParameterError as exc:
        flags = [FLAGS[n] for n in getattr(exc, "params", ()) if n in FLAGS]
        if not flags:
            raise
        raise ParameterError(f"{' and '.join(flags)}: {exc}") from None


def params_from_flags(a: argparse.Namespace, base, exclude: Iterable[str] = ()):
    """``base`` with the values the user gave by flag; a refused value names its flag."""
    with flags_named():
        return base.replace(**changes_from_flags(a, type(base), exclude))


def check_flag_values(a: argparse.Namespace) -> None:
    """Refuse a flag's value that its declaration refuses on its own (out of range, say), naming the flag, as
    the command would once it has built its parameters: the command line says so before it loads any of
    the pipeline. A field two classes declare is refused here only when every declaration refuses it."""
    with flags_named():
        for name, flag in FLAGS.items():
            value = getattr(a, dest_of(flag), None)
            if value is not None and not any(spec.accepts(value) for spec in SPECS[name]):
                raise refusal(name, SPECS[name][0], value)
