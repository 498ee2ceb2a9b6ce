"""Visualisation task type: ``viz.rerun`` (MCAP → rerun .rrd; extra ``viz``)."""
