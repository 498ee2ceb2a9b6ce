"""Records of what ran: lineage, run records, and MCAP files with their own lineage.

Run records are MCAP files, one per workflow.

Public API (import from here; the submodules are private)::

    Lineage, LineageInput           who made an attempt's outputs (pure data)
    LineageMcapWriter               MCAP writer for task code, stamps ``osmo.lineage`` on close
    JsonMcapWriter                  the same without lineage
    McapFile                        read any MCAP file (channels, messages, metadata, attachments)
    read_lineage(path)              the lineage an MCAP file carries, or None
    write_run_record(path, ...)     a finished workflow's run record (status, lineage, and
                                    foxglove.Log lines on LOG_TOPIC)
    read_run_record(path)           and back
    RecordError                     an unreadable MCAP file (a UsageError, exit code 2)

Only :mod:`osmo.record.mcapio` imports ``mcap``; only :mod:`osmo.record.foxlog` imports
protobuf. Nothing here imports the server or scheduler.
"""

from __future__ import annotations

from osmo.record.lineage import LINEAGE_METADATA, Lineage, LineageInput
from osmo.record.mcapio import (
    JsonMcapWriter,
    LineageMcapWriter,
    McapFile,
    RecordError,
    read_lineage,
)
from osmo.record.runrecord import (
    LINEAGE_TOPIC,
    LOG_TOPIC,
    LOGS_TOPIC,
    STATUS_TOPIC,
    WORKFLOW_METADATA,
    read_run_record,
    write_run_record,
)

__all__ = [
    "LINEAGE_METADATA",
    "LINEAGE_TOPIC",
    "LOG_TOPIC",
    "LOGS_TOPIC",
    "STATUS_TOPIC",
    "WORKFLOW_METADATA",
    "JsonMcapWriter",
    "Lineage",
    "LineageInput",
    "LineageMcapWriter",
    "McapFile",
    "RecordError",
    "read_lineage",
    "read_run_record",
    "write_run_record",
]
