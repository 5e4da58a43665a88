"""The version of thetahat: the one place it is written (``pyproject.toml`` reads it)."""

__version__ = "0.4.0.dev0"
