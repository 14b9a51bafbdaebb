"""``python -m stack.train`` is ``stack-train``."""

from .cli import main

raise SystemExit(main())
