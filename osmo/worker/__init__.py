"""Workers: attempt folders, log records, and the local pool of host processes."""

from osmo.worker.logs import LogRecord, LogWriter, read_log
from osmo.worker.pool import LocalPool, kill_stale, process_start_time
from osmo.worker.workdir import Launch, PrepareError, prepare, promote

__all__ = [
    "Launch",
    "LocalPool",
    "LogRecord",
    "LogWriter",
    "PrepareError",
    "kill_stale",
    "prepare",
    "process_start_time",
    "promote",
    "read_log",
]
