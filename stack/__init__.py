"""Hardware-in-the-loop-ready multi-robot formation control stack."""

from . import numerics as _numerics

_numerics.pin()  # before numpy loads OpenBLAS: a step log replays to the bit on another x86-64 machine

__version__ = "0.1.0"
