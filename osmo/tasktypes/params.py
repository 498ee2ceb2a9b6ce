"""The parameter rules, now in :mod:`osmo.params`; re-exported here.

They moved to the bottom layer, so the spec layer can check params without importing task types;
existing importers keep working.
"""

from osmo.params import SIMPLE_TYPES, fill_defaults, schema_problems, type_label, value_problem

__all__ = ["SIMPLE_TYPES", "fill_defaults", "schema_problems", "type_label", "value_problem"]
