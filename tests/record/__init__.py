"""Tests of osmo.record: lineage, run records and lineage-stamped MCAP files."""
