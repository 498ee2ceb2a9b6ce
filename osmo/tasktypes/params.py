"""The parameter rules, now in :mod:`osmo.params` (the bottom layer, so the spec layer can
check params without importing task types); re-exported here for existing importers."""

from osmo.params import SIMPLE_TYPES, fill_defaults, schema_problems, type_label, value_problem

__all__ = ["SIMPLE_TYPES", "fill_defaults", "schema_problems", "type_label", "value_problem"]
