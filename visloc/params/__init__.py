"""Every parameter of every stage, declared once: typed, frozen, validated dataclasses with the
paper's values as presets.

* ``declare``: how a parameter is declared (``param``, ``Spec``, ``Control``) and checked;
* ``paper``: SIFT, the correspondence tests, retrieval and the Kalman filter, and Table 1;
* ``refined``: the refined measurement and gate, the fast retrieval, a run at camera rate;
* ``options``: the commands' own options (how much of a drive, processes, tiles, port) and ``visloc bench``'s.

The command line's flags, the dashboard's controls, ``--help`` and ``docs/parameters.md``
(``python -m visloc.params``) are all made from these declarations. Imports only
``visloc.errors`` and ``visloc.stats``.
"""

from __future__ import annotations

from visloc.params.declare import (AUTO, MAX_C_INT, MAX_VARIANCE, METHODS_ALL, MIN_VARIANCE, Control, Params, Spec,
                                   check, declared, flag_of, param, refusal, refuse, spec_of, value_text)
from visloc.params.paper import (MAX_DT_S, MAX_GEOTAG_SIGMA_M, MAX_SECONDS, METRES_PER_DEGREE, MIN_DT_S,
                                 PAPER_EVAL_RETRIEVAL, PAPER_FILTER, PAPER_MATCH, PAPER_RETRIEVAL, PAPER_SIFT,
                                 STORE_SIFT, FilterParams, MatchParams, RetrievalParams, SiftParams)
from visloc.params.options import BENCH, BENCH_WORKERS, COMMAND_OPTIONS, BenchParams, CommandOptions
from visloc.params.refined import FAST, NN_BACKENDS, REFINED, TRACK, FastParams, RefinedParams, TrackParams

# every parameter class, in the order the docs list them
PARAMETER_CLASSES = (SiftParams, MatchParams, RetrievalParams, FilterParams, RefinedParams, FastParams, TrackParams,
                     CommandOptions, BenchParams)



def dashboard_controls() -> list[tuple[type, str, Spec, object]]:
    """(class, name, spec, default) of every parameter with a dashboard control, in declaration order."""
    return [(cls, name, spec, default) for cls in PARAMETER_CLASSES for name, spec, default in declared(cls)
            if spec.control is not None]


__all__ = [
    "AUTO", "BENCH", "BENCH_WORKERS", "COMMAND_OPTIONS", "BenchParams", "CommandOptions", "FAST", "MAX_C_INT", "MAX_DT_S", "MAX_GEOTAG_SIGMA_M", "MAX_SECONDS", "MAX_VARIANCE", "METHODS_ALL",
    "METRES_PER_DEGREE", "MIN_DT_S", "MIN_VARIANCE", "NN_BACKENDS", "PAPER_EVAL_RETRIEVAL", "PAPER_FILTER",
    "PAPER_MATCH", "PAPER_RETRIEVAL", "PAPER_SIFT", "PARAMETER_CLASSES", "REFINED", "STORE_SIFT", "TRACK", "Control", "FastParams",
    "FilterParams", "MatchParams", "Params", "RefinedParams", "RetrievalParams", "SiftParams", "Spec", "TrackParams",
    "check", "dashboard_controls", "declared", "flag_of", "param", "parameter_table_markdown", "refusal", "refuse", "spec_of",
    "value_text",
]


def parameter_table_markdown() -> str:
    """``docs/parameters.md``: every declared parameter, by stage, with its flag, unit, range, default and help."""
    lines = ["# Parameters", "",
             "Every parameter visloc has, generated from their declarations in `visloc/params/` by "
             "`python -m visloc.params > docs/parameters.md` (a test fails when this page differs). The command "
             "line's flags, their `--help` and the dashboard's controls are made from the same declarations.", ""]
    for cls in PARAMETER_CLASSES:
        doc = (cls.__doc__ or "").strip().split("\n\n")[0].replace("\n", " ")
        doc = " ".join(doc.split())
        lines += [f"## `{cls.__name__}`", "", doc, "",
                  "| parameter | flag | unit | valid | default | used by | what it does | dashboard |",
                  "|---|---|---|---|---|---|---|---|"]
        for name, spec, default in declared(cls):
            flag = flag_of(name, spec)
            control = spec.control.label if spec.control else ""
            help_text = spec.help.replace("|", "\\|")
            lines.append(f"| `{name}` | {f'`{flag}`' if flag else '–'} | {spec.unit or '–'} | {spec.rule()} | "
                         f"{value_text(default) if default is not None else spec.when_unset} | {', '.join(spec.methods)} | {help_text} | {control or '–'} |")
        lines.append("")
    return "\n".join(lines)
