"""Parameters validate themselves and name the culprit."""

import math

import pytest

from visloc.errors import ParameterError
from visloc.params import (PAPER_FILTER, PAPER_MATCH, FilterParams, MatchParams, RetrievalParams, SiftParams,
                           METRES_PER_DEGREE)


@pytest.mark.parametrize("cls,kwargs,name", [
    (MatchParams, {"tau1": 0.0}, "tau1"),
    (MatchParams, {"tau1": 1.01}, "tau1"),
    (MatchParams, {"tau1": math.nan}, "tau1"),
    (MatchParams, {"tau2": -1.5}, "tau2"),
    (MatchParams, {"tau2": 1.2}, "tau2"),
    (FilterParams, {"meas_var_m2": -1.0}, "meas_var_m2 (R)"),
    (FilterParams, {"accel_var_m2_s4": -0.1}, "accel_var_m2_s4 (Q)"),
    (FilterParams, {"init_var": -5.0}, "init_var (P0)"),
    (FilterParams, {"dt_s": 0.0}, "dt_s"),
    (RetrievalParams, {"window_s": 0.0}, "window_s"),
    (RetrievalParams, {"exclusion_s": -1.0}, "exclusion_s"),
    (SiftParams, {"n_features": -1}, "n_features"),
    (SiftParams, {"sigma": 0.0}, "sigma"),
])
def test_out_of_range_is_refused_naming_the_parameter(cls, kwargs, name):
    with pytest.raises(ParameterError) as err:
        cls(**kwargs)
    assert str(err.value).startswith(name + "=")
    assert "\n" not in str(err.value)


@pytest.mark.parametrize("tau1,tau2", [(1.0, -1.0), (1e-9, 1.0), (0.8, 0.97)])
def test_bounds_are_inclusive_as_the_paper_states(tau1, tau2):
    """tau1 in (0, 1], tau2 in [-1, 1]: the closed ends are accepted and kept as given (the open end,
    tau1 = 0, is refused in test_out_of_range_is_refused_naming_the_parameter)."""
    params = MatchParams(tau1=tau1, tau2=tau2)
    assert (params.tau1, params.tau2) == (tau1, tau2)


def test_paper_preset_holds_table_1():
    assert (PAPER_MATCH.tau1, PAPER_MATCH.tau2) == (0.8, 0.97)
    assert PAPER_FILTER.dt_s == 1.0 and PAPER_FILTER.init_var == 1000.0
    # R = (0.0001 deg of arc)^2 = 11.12 m standard deviation
    assert math.sqrt(PAPER_FILTER.meas_var_m2) == pytest.approx(11.1195, abs=1e-4)
    assert METRES_PER_DEGREE == pytest.approx(111_195.08, abs=0.01)


def test_replace_rejects_unknown_names():
    assert PAPER_MATCH.replace(tau1=0.7).tau1 == 0.7
    with pytest.raises(ParameterError, match="tau3"):
        PAPER_MATCH.replace(tau3=0.1)
