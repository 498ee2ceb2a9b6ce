"""What this release of osmo does not support yet: one table, so later work removes entries.

Each key names a spec feature (``task.<field>``, ``inputs.<kind>``, ``outputs.<kind>``); its
value is the message shown when a spec uses it. The parsers still read the feature's shape into
the model where the model has room for it; validation then rejects it with this message.
"""

from __future__ import annotations

__all__ = ["UNSUPPORTED"]

_PLATFORM = "is not supported by osmo's process runtime; remove it"

UNSUPPORTED: dict[str, str] = {
    "task.volumeMounts": f"'volumeMounts' {_PLATFORM}",
    "task.privileged": f"'privileged' {_PLATFORM}",
    "task.hostNetwork": f"'hostNetwork' {_PLATFORM}",
}
