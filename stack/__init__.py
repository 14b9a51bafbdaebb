"""Hardware-in-the-loop-ready multi-robot formation control stack."""

__version__ = "0.1.0"
