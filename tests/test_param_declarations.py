"""Every parameter is declared once; the command line, its --help, the dashboard's controls and the docs'
parameter table are made from the declarations. These tests fail when any of them drifts."""

from __future__ import annotations

import argparse
import math
from dataclasses import dataclass, fields
from pathlib import Path

import pytest

from visloc.cli import commands
from visloc.cli import parser as cli
from visloc.errors import ParameterError
from visloc.cli.param_flags import FLAGS, add_param_flags, changes_from_flags, dest_of, params_from_flags
from visloc.params import (PARAMETER_CLASSES, PAPER_FILTER, Control, FastParams, FilterParams, MatchParams, Params,
                           RefinedParams, RetrievalParams, SiftParams, TrackParams, dashboard_controls, declared,
                           flag_of, param, parameter_table_markdown)

ROOT = Path(__file__).resolve().parent.parent

# which parameter classes each command takes (the fields a command sets itself are left out)
COMMAND_CLASSES = {
    "ingest": (SiftParams,),
    "localize": (SiftParams, MatchParams, RetrievalParams, FilterParams, RefinedParams, FastParams),
    "evaluate": (SiftParams, MatchParams, RetrievalParams, FilterParams, RefinedParams, FastParams),
    "evaluate-drives": (SiftParams, MatchParams, RetrievalParams, FilterParams, RefinedParams, FastParams),
    "track": (SiftParams, TrackParams, FilterParams, RefinedParams, FastParams),
}
SET_BY_COMMAND = {("track", "dt_s")}  # track's time step is the frame interval


def _subparser(name: str) -> argparse.ArgumentParser:
    parser = cli.build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return sub.choices[name]


def _flagged(cls):
    return [(name, spec, flag_of(name, spec)) for name, spec, _ in declared(cls) if flag_of(name, spec)]


def test_the_docs_parameter_table_is_generated_from_the_declarations():
    page = (ROOT / "docs" / "parameters.md").read_text()
    assert page == parameter_table_markdown(), "run: python -m visloc.params > docs/parameters.md"


def test_every_field_of_every_parameter_class_is_declared():
    for cls in PARAMETER_CLASSES:
        undeclared = [f.name for f in fields(cls) if "spec" not in f.metadata]
        assert not undeclared, f"{cls.__name__}: {undeclared} lack a declaration (visloc.params.param)"
        for name, spec, default in declared(cls):
            assert spec.help and spec.methods, (cls.__name__, name)
            assert spec.accepts(default), f"{cls.__name__}.{name}: default {default!r} outside {spec.rule()}"


@pytest.mark.parametrize("command", sorted(COMMAND_CLASSES))
def test_every_declared_flag_is_on_its_commands_with_the_declared_help(command):
    parser = _subparser(command)
    actions = {flag: a for a in parser._actions for flag in a.option_strings}
    help_text = " ".join(parser.format_help().split())
    for cls in COMMAND_CLASSES[command]:
        for name, spec, flag in _flagged(cls):
            if (command, name) in SET_BY_COMMAND:
                assert flag not in actions, (command, flag)
                continue
            assert flag in actions, f"{command}: {cls.__name__}.{name} has no {flag}"
            assert actions[flag].dest == dest_of(flag)
            first_words = " ".join(spec.help.split()[:6])
            assert first_words in help_text or "default: 1 when the database" in (actions[flag].help or ""), \
                (command, flag)


@pytest.mark.parametrize("command", sorted(COMMAND_CLASSES))
def test_a_value_out_of_range_is_refused_naming_the_flag_the_user_typed(command):
    """For every bounded declared parameter a command takes: a value just outside its range, given by its
    flag, is refused with a message that starts with that flag."""
    base_args = {"ingest": ["ingest", "x.csv"], "localize": ["localize", "x.csv"], "evaluate": ["evaluate"],
                 "evaluate-drives": ["evaluate-drives"], "track": ["track", "x.csv"]}[command]
    tried = 0
    for cls in COMMAND_CLASSES[command]:
        for name, spec, flag in _flagged(cls):
            if (command, name) in SET_BY_COMMAND or spec.low is None or spec.kind not in ("number", "integer"):
                continue
            bad = spec.low - 1 if spec.kind == "integer" else (spec.low if spec.open_low else spec.low - 1e-3)
            bad_text = str(int(bad)) if spec.kind == "integer" else repr(float(bad))
            a = cli.build_parser().parse_args([*base_args, flag, bad_text])
            with pytest.raises(ParameterError) as err:
                commands.sift_params(a)
                if command != "ingest":
                    match, retrieval, filt = commands.method_params(a) if command != "track" else (None, None, None)
                    if command == "track":
                        params_from_flags(a, TrackParams(), exclude=("exclusion_s",) if a.exclusion_s is None else ())
                        filt = params_from_flags(a, PAPER_FILTER, exclude=("dt_s",))
                    commands.with_method_flags(a, commands.REFINED_METHOD, filt.init_var)
            assert str(err.value).startswith(flag + ": " + name), (command, flag, str(err.value))
            tried += 1
    assert tried >= (4 if command == "ingest" else 12)


def test_flags_of_different_classes_never_collide():
    seen: dict[str, str] = {}
    for cls in PARAMETER_CLASSES:
        for name, _, flag in _flagged(cls):
            assert seen.setdefault(flag, name) == name, f"{flag} names both {seen[flag]} and {name}"
    assert FLAGS["tau1"] == "--tau1" and FLAGS["n_features"] == "--sift-features"


def test_a_new_declared_parameter_gets_its_flag_help_check_and_message_without_other_code():
    @dataclass(frozen=True)
    class NewParams(Params):
        """A parameter class as a new stage would declare it."""

        speed_limit_m_s: float = param(30.0, "fastest the car is expected to drive", unit="m/s", low=0,
                                       open_low=True)

    parser = argparse.ArgumentParser(prog="visloc")
    add_param_flags(parser, NewParams, NewParams())
    assert "fastest the car is expected to drive; > 0 m/s (default 30)" in " ".join(parser.format_help().split())
    a = parser.parse_args(["--speed-limit-m-s", "12.5"])
    assert changes_from_flags(a, NewParams) == {"speed_limit_m_s": 12.5}
    assert params_from_flags(a, NewParams()).speed_limit_m_s == 12.5
    with pytest.raises(ParameterError, match=r"^speed_limit_m_s=-1\.0: must be > 0 m/s$"):
        NewParams(speed_limit_m_s=-1.0)
    with pytest.raises(ParameterError, match=r"must be > 0 m/s"):
        params_from_flags(parser.parse_args(["--speed-limit-m-s", "nan"]), NewParams())


def test_every_bounded_parameter_refuses_values_outside_its_declared_range():
    for cls in PARAMETER_CLASSES:
        for name, spec, default in declared(cls):
            if spec.kind not in ("number", "integer"):
                continue
            cls(**{name: default})  # the default is valid
            bad = [math.nan, math.inf] if spec.kind == "number" else [1.5, True]
            if spec.low is not None:
                bad.append(spec.low if spec.open_low else spec.low - 1)
            if spec.high is not None:
                bad.append(spec.high if spec.open_high else spec.high + 1)
            for value in bad:
                with pytest.raises(ParameterError) as err:
                    cls(**{name: value})
                assert str(err.value).split("=")[0].split(" ")[0] == name and err.value.params == (name,)


def test_the_dashboard_has_a_control_for_every_declared_one_and_its_values_are_the_parameters():
    from dataclasses import replace

    from visloc.dashboard.gui import paper_values, shown_initial
    from visloc.dashboard.state import Controls

    controlled = dashboard_controls()
    names = [name for _, name, _, _ in controlled]
    assert {"tau1", "tau2", "meas_var_m2", "accel_var_m2_s4", "init_var", "gate_chi2", "exclusion_s",
            "window_s"} <= set(names)
    shown = paper_values()["params"]
    c = Controls(store_request=(1, "s"))
    assert set(c.params) == set(names) == set(shown)
    for _, name, spec, default in controlled:
        control: Control = spec.control
        assert control.folder in ("matching", "filter", "queries"), name
        assert control.low <= shown[name] <= control.high, f"{name}: first value outside its slider"
        assert shown[name] == shown_initial(spec, default)
        assert control.from_shown(control.to_shown(4.0)) == pytest.approx(4.0)
    # the controls' values are the engine's parameters, in the parameters' own units
    assert c.filter_params() == PAPER_FILTER
    moved = replace(c, params={**c.params, "meas_var_m2": 2.0 ** 2, "tau1": 0.7}, rate_hz=2.0)
    assert moved.filter_params() == PAPER_FILTER.replace(meas_var_m2=4.0, dt_s=0.5)
    assert moved.params_for(MatchParams()) == MatchParams(tau1=0.7)
    assert moved.match_key(("d",)) != c.match_key(("d",)) and moved.filter_key() != c.filter_key()
