"""Runtimes: how an attempt's command is run (host processes today; containers later)."""

from osmo.runtime.process.groups import (
    ProcessHandle,
    ProcessRuntime,
    Runtime,
    StartError,
    exit_code_of,
)
from osmo.runtime.process.proctable import kill_stale, process_start_time

__all__ = [
    "ProcessHandle",
    "ProcessRuntime",
    "Runtime",
    "StartError",
    "exit_code_of",
    "kill_stale",
    "process_start_time",
]
