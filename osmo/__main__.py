"""``python -m osmo`` runs the CLI."""

from osmo.cli.main import entry

entry()
