"""``python -m visloc.params``: print the parameter table of docs/parameters.md."""

from visloc.params import parameter_table_markdown

print(parameter_table_markdown(), end="")
