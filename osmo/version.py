"""osmo's version, for what records it (lineage, MCAP files); ``osmo.__version__`` too.

The bottom layer: any module may import it without importing the package's public facade.
"""

__all__ = ["__version__"]

__version__ = "0.1.0"
