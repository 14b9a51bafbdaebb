"""What our messages look like in Foxglove, and the writer that records / serves them: shared by the fleet's
recorder (``stack.fleet.record``) and a robot's own view (``stack-agent --record / --viz``).

A room of its own: it imports ``stack.comm``, ``stack.scenario`` and ``stack.models``, never the world, the
fleet or the agents. The Foxglove SDK comes with the ``viz`` extra (the ``sim`` extra has it too); this
module imports nothing of it, so a robot's core install can still say what is missing in one line.
"""

from __future__ import annotations

EXTRA = "viz"
"""The extra (``pyproject.toml``) that installs the Foxglove SDK."""


class RecorderError(RuntimeError):
    """The recording or the live server could not start (one line: a path, a port in use)."""


class VizUnavailable(RuntimeError):
    """The Foxglove SDK is not installed here (one line naming the extra)."""


def require_sdk(what: str) -> None:
    """Raise :class:`VizUnavailable` (one line: ``what`` needs it, and the extra) unless ``foxglove`` imports."""
    try:
        import foxglove  # noqa: F401
    except ModuleNotFoundError as e:
        raise VizUnavailable(f"{what} needs the Python package {e.name!r}, not installed here (install the "
                             f"'{EXTRA}' extra: pip install 'formation-stack[{EXTRA}]')") from None
